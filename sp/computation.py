"""Computation: attributes integrated over each group of pixels (the SP computation function).

Reference 001, 4.5.1 (computation: "attributes of the hypothesized entity ... integrated over
the group"), 4.4.2 (entity frame attributes). Every attribute is computed for all segments at
once: the per-segment sums, minima and maxima in compiled passes over the pixels (numba), so
the cost is a few passes over the grouped pixels whatever the number of groups, and what
follows from them vectorised over the segments. The numpy definitions the compiled forms are
tested against are test oracles, in ``tests/kernel_reference/computation_reference.py``.

World frame (z up); metres, radians, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from core.errors import EngineError
from sp.nan_ops import minimum as _minimum


class ComputationError(EngineError, ValueError):
    """Inputs of mismatched shapes; names them."""


@dataclass(slots=True)
class SegmentAttributes:
    """Attributes of K segments (arrays of length K, world frame).

    n_pixels:        (K,) int64 returns in the segment.
    centroid_xyz:    (K, 3) float64 mean of the points, m.
    center_xyz:      (K, 3) float64 centre of the oriented footprint box (x, y) at half height, m.
    yaw_rad:         (K,) heading of the footprint's long axis (major principal axis), rad.
    length_m, width_m, height_m: (K,) extents along the long axis, across it, and above the
                     ground under the segment.
    ground_z_m:      (K,) ground height under the segment (m), from the ground pixels below it.
    clearance_m:     (K,) height of the segment's lowest point above that ground (m, >= 0).
    area_m2, volume_m3: (K,) footprint area (length x width) and box volume.
    intensity:       (K,) mean intensity (sensor units).
    curvature:       (K,) smallest over summed eigenvalue of the 3D scatter (0 plane, 1/3 ball).
    verticality:     (K,) |z| of the scatter's normal (smallest eigenvector): 0 wall, 1 flat.
    thickness_m, breadth_m: (K,) standard deviation of the points along the scatter's normal
                     and along its middle axis (a planar patch: thin and broad).
    range_m:         (K,) nearest range from the sensor.
    t_offset_ns:     (K,) int64 mean time of the segment's returns after the sweep's stamp.
    """

    n_pixels: np.ndarray
    centroid_xyz: np.ndarray
    center_xyz: np.ndarray
    yaw_rad: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    height_m: np.ndarray
    ground_z_m: np.ndarray
    clearance_m: np.ndarray
    area_m2: np.ndarray
    volume_m3: np.ndarray
    intensity: np.ndarray
    curvature: np.ndarray
    verticality: np.ndarray
    thickness_m: np.ndarray
    breadth_m: np.ndarray
    range_m: np.ndarray
    t_offset_ns: np.ndarray

    def __len__(self) -> int:
        return int(self.n_pixels.shape[0])

    def take(self, keep: np.ndarray) -> SegmentAttributes:
        """The segments selected by ``keep`` (bool mask or indices), in order."""
        return SegmentAttributes(**{k: getattr(self, k)[keep] for k in self.__slots__})


def ground_below(
    ground: np.ndarray,
    z_world: np.ndarray,
    r_m: np.ndarray | None = None,
    max_slope: float = 0.3,
    max_reach_m: float = 15.0,
) -> np.ndarray:
    """(H, W) float64: for each pixel the world height of the ground below it in its column
    (rows grow downwards), NaN where the column has none below.

    Without ``r_m`` it is the height of the nearest ground return below. With ``r_m`` ((H, W)
    horizontal range from the sensor, m) the ground is continued from that return along the
    slope of the column's last two ground returns (reference 001, 4.5.2: grouping by
    continuity), the slope clipped to +-``max_slope`` and the reach to ``max_reach_m``, so a
    patch of a hillside seen past a gap is not taken for an object standing on the lower
    ground in front of it. One compiled pass (:func:`_ground_below_kernel`); the same
    heights as ``ground_below_reference`` (the numpy definition).
    """
    if r_m is not None and r_m.shape != ground.shape:
        raise ComputationError(f"r_m {r_m.shape} does not match ground {ground.shape}")
    if z_world.shape != ground.shape:
        raise ComputationError(f"z_world {z_world.shape} does not match ground {ground.shape}")
    return _ground_below_kernel(
        np.ascontiguousarray(ground, dtype=np.bool_),
        np.ascontiguousarray(z_world, dtype=np.float64),
        np.ascontiguousarray(np.zeros_like(z_world) if r_m is None else r_m, dtype=np.float64),
        r_m is not None,
        float(max_slope),
        float(max_reach_m),
    )


@numba.njit(cache=True, nogil=True)
def _clip(x, lo, hi):
    """``np.clip`` of one float (NaN stays NaN)."""
    if x != x:
        return x
    return lo if x < lo else (hi if x > hi else x)


@numba.njit(cache=True, nogil=True)
def _ground_below_kernel(ground, z_world, r_m, continued, max_slope, max_reach_m):
    """``ground_below_reference`` row by row from the bottom, each column's last ground
    height, range and slope in arrays (W,)."""
    H, W = ground.shape
    out = np.empty((H, W))
    z1 = np.full(W, np.nan)
    r1 = np.zeros(W)
    slope = np.zeros(W)
    for i in range(H - 1, -1, -1):
        for j in range(W):
            if continued:
                out[i, j] = z1[j] + slope[j] * _clip(r_m[i, j] - r1[j], 0.0, max_reach_m)
            else:
                out[i, j] = z1[j]
            if ground[i, j]:
                if continued:
                    dr = r_m[i, j] - r1[j]
                    if np.isfinite(z1[j]) and dr > 0.5:
                        slope[j] = _clip((z_world[i, j] - z1[j]) / dr, -max_slope, max_slope)
                    r1[j] = r_m[i, j]
                z1[j] = z_world[i, j]
    return out


def segment_attributes(
    labels: np.ndarray,
    points_world: np.ndarray,
    intensity: np.ndarray,
    range_m: np.ndarray,
    t_offset_ns: np.ndarray,
    ground_z: np.ndarray,
    n_segments: int | None = None,
) -> SegmentAttributes:
    """Attributes of every segment of ``labels`` ((H, W) int, -1 none, 0..K-1).

    points_world: (H, W, 3) float world points, m; intensity: (H, W) float sensor units (NaN
    counts as 0, infinities as the largest float, as ``np.nan_to_num``); range_m: (H, W)
    float, m; t_offset_ns: (H, W) int64, ns; ground_z: (H, W) float ground height below each
    pixel, m, non-finite where unknown (see :func:`ground_below`). ``n_segments``: K, at
    least the largest label + 1 (segments without pixels get zero extents and infinite
    range); by default the largest label + 1.

    Compiled passes (numba) over the labelled pixels: :func:`_segment_runs` finds them as
    runs along the rows and groups the runs by segment; :func:`_segment_sums` takes each
    segment's sums, minima and maxima, then the products of the offsets from its centroid;
    :func:`_segment_box` its extents along and across the yaw, and the box. The 3 x 3
    eigen-decompositions and the trigonometry stay numpy, vectorised over the K segments,
    as in the reference. Each sum adds a segment's pixels in flat order, the order
    ``np.bincount`` adds them in ``segment_attributes_reference``, and every expression
    is the reference's, so the results are the reference's to the last bit (tested).
    Non-finite points make the decomposition fail (``np.linalg.LinAlgError``), as in the
    reference.
    """
    if points_world.shape[:2] != labels.shape or points_world.shape[2:] != (3,):
        raise ComputationError(f"points {points_world.shape} do not match labels {labels.shape}")
    for name, a in (
        ("intensity", intensity),
        ("range_m", range_m),
        ("t_offset_ns", t_offset_ns),
        ("ground_z", ground_z),
    ):
        if np.shape(a) != labels.shape:
            raise ComputationError(f"{name} {np.shape(a)} does not match labels {labels.shape}")
    lab = np.ascontiguousarray(labels).reshape(-1)
    p = np.ascontiguousarray(points_world).reshape(-1, 3)
    runs, first = _segment_runs(lab, -1 if n_segments is None else int(n_segments))
    K = first.shape[0] - 1
    if n_segments is not None and K > n_segments:
        # the kernel sized the segments by the largest label; the caller asked for fewer
        raise ComputationError(f"label {K - 1} in labels but n_segments is {n_segments}")
    n, c, cov, z0, z1, g_n, g_sum, i_sum, r_min, t_sum = _segment_sums(
        runs,
        first,
        p,
        np.ascontiguousarray(intensity).reshape(-1),
        np.ascontiguousarray(range_m).reshape(-1),
        np.ascontiguousarray(t_offset_ns).reshape(-1),
        np.ascontiguousarray(ground_z).reshape(-1),
    )
    n_safe = np.maximum(n, 1)
    # the decomposition exactly as the reference (same matrices in, same numbers out)
    evals, evecs = np.linalg.eigh(cov + 1e-9 * np.eye(3))
    curvature = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-12)
    verticality = np.abs(evecs[:, 2, 0])
    yaw = 0.5 * np.arctan2(2 * cov[:, 0, 1], cov[:, 0, 0] - cov[:, 1, 1])
    # numpy's cos / sin (not the kernel's libm ones, which may differ in the last bit)
    cos, sin = np.cos(yaw), np.sin(yaw)
    center, length, width, height, gz, clearance, area, volume = _segment_box(
        runs, first, p, c, cos, sin, z0, z1, g_n, g_sum
    )
    return SegmentAttributes(
        n_pixels=n,
        centroid_xyz=c,
        center_xyz=center,
        yaw_rad=yaw,
        length_m=length,
        width_m=width,
        height_m=height,
        ground_z_m=gz,
        clearance_m=clearance,
        area_m2=area,
        volume_m3=volume,
        intensity=i_sum / n_safe,
        curvature=curvature,
        verticality=verticality,
        thickness_m=np.sqrt(np.maximum(evals[:, 0], 0.0)),
        breadth_m=np.sqrt(np.maximum(evals[:, 1], 0.0)),
        range_m=r_min,
        t_offset_ns=np.round(t_sum / n_safe).astype(np.int64),
    )


#: a segment needs this many row triples (three returns of it side by side in one scan row)
#: for its roughness to be known: fewer are a few noisy second differences
ROUGHNESS_MIN_TRIPLES = 5
#: the texture is resolved to this (m); a second difference over the last bin's upper edge
#: counts in the last bin, which holds the jumps between objects
ROUGHNESS_BIN_M = 0.01
ROUGHNESS_BINS = 128


def segment_roughness(
    labels: np.ndarray,
    range_m: np.ndarray,
    n_segments: int,
    min_triples: int = ROUGHNESS_MIN_TRIPLES,
) -> np.ndarray:
    """(K,) float64 texture of each segment (reference 001, 4.5.6: "differences in range at
    adjacent pixels can be used to compute ... surface roughness, or texture"), metres: the
    median over its row triples of ``|r[j-1] - 2 r[j] + r[j+1]|``, the range's second
    difference along a scan row between three returns of the segment, to
    ``ROUGHNESS_BIN_M``; NaN for a segment with fewer than ``min_triples`` triples.

    labels: (H, W) int segment per pixel (-1 none), 0..n_segments-1; range_m: (H, W) float
    range of each pixel, m. Columns wrap (a full turn of azimuth). A smooth surface (a car's
    body, a rock, a wall) gives about the range noise (a few centimetres) whatever its slope,
    as its ranges change linearly along a row; leaves scatter a LADAR's returns in depth
    (a bush or a crown gives decimetres). The median, not the mean, because a real car's
    windows let some returns through to its inside, and a segment over two objects side by
    side jumps in range where one meets the other: a few triples, not the surface. One
    compiled pass counts each segment's second differences in bins of ``ROUGHNESS_BIN_M``
    (:func:`_roughness_histogram`); the median is the middle triple's bin centre.
    """
    if np.shape(range_m) != np.shape(labels):
        raise ComputationError(f"range_m {np.shape(range_m)} does not match labels {labels.shape}")
    hist = _roughness_histogram(
        np.ascontiguousarray(labels, dtype=np.int64),
        np.ascontiguousarray(range_m, dtype=np.float64),
        int(n_segments),
        ROUGHNESS_BIN_M,
        ROUGHNESS_BINS,
    )
    n = hist.sum(axis=1)
    # the bin of each segment's middle triple (0-based rank n // 2)
    below = np.cumsum(hist, axis=1) <= (n // 2)[:, None]
    middle = below.sum(axis=1)
    return np.where(n >= min_triples, (middle + 0.5) * ROUGHNESS_BIN_M, np.nan)


@numba.njit(cache=True, nogil=True)
def _roughness_histogram(labels, r, K, bin_m, n_bins):  # pragma: no cover
    """(K, n_bins) int64: per segment of ``labels`` (H, W), how many of its row triples have a
    second difference of range ``r`` (H, W) in each bin of ``bin_m`` (the last bin open)."""
    H, W = labels.shape
    out = np.zeros((K, n_bins), np.int64)
    for i in range(H):
        for j in range(W):
            s = labels[i, j]
            if s < 0 or s >= K:
                continue
            jl = j - 1 if j > 0 else W - 1
            jr = j + 1 if j < W - 1 else 0
            if labels[i, jl] != s or labels[i, jr] != s:
                continue
            d = abs(r[i, jl] - 2.0 * r[i, j] + r[i, jr]) / bin_m
            if d != d:  # a range unknown: no triple
                continue
            out[s, int(d) if d < n_bins else n_bins - 1] += 1
    return out


@numba.njit(cache=True, nogil=True)
def _label_runs(lab):  # pragma: no cover
    """The runs of one label in ``lab`` (N,) int, in flat order: (R, 3) int64 rows of
    label, start, stop (negative labels, no segment, left out)."""
    N = lab.shape[0]
    # sized for the worst case (every pixel a run) rather than grown, as an array
    # reassigned in the loop costs numba reference counting on every pixel
    raw = np.empty((N, 3), np.int64)
    R = 0
    prev = -1
    for i in range(N):
        s = lab[i]
        if s != prev:  # mispredicted at run ends only
            if prev >= 0:
                raw[R - 1, 2] = i
            if s >= 0:
                raw[R, 0] = s
                raw[R, 1] = i
                R += 1
            prev = s
    if prev >= 0:
        raw[R - 1, 2] = N
    return raw[:R]


@numba.njit(cache=True, nogil=True)
def _segment_runs(lab, n_segments):  # pragma: no cover
    """The labelled pixels as runs of one label in flat order, grouped by segment.

    lab (N,) int labels (-1 or any negative: none); n_segments: K, or -1 for the largest
    label + 1 (K is never less than that, so the caller checks it against what it asked for).

    Returns ``runs`` (R, 2) int64 the [start, stop) flat pixel ranges, those of segment 0
    first, each segment's in flat order (so a segment's pixels are visited in the order
    ``np.bincount`` visits them in the reference), and ``first`` (K + 1,) int64: segment s
    owns ``runs[first[s]:first[s + 1]]``. A segment's pixels lie in a few row-long runs, so
    the passes over them read the pixel arrays in order.
    """
    # the scan in a function of its own and the largest label from the runs: both keep
    # the scan's loop tight (each cost it about a third more time, numba 0.68)
    raw = _label_runs(lab)
    R = raw.shape[0]
    top = -1
    for r in range(R):
        top = max(top, raw[r, 0])
    K = max(top + 1, n_segments)
    # counting sort of the runs by label, stable (flat order within a segment)
    first = np.zeros(K + 1, np.int64)
    for r in range(R):
        first[raw[r, 0] + 1] += 1
    for s in range(K):
        first[s + 1] += first[s]
    fill = first[:K].copy()
    runs = np.empty((R, 2), np.int64)
    for r in range(R):
        s = raw[r, 0]
        runs[fill[s], 0] = raw[r, 1]
        runs[fill[s], 1] = raw[r, 2]
        fill[s] += 1
    return runs, first


@numba.njit(cache=True, nogil=True)
def _segment_sums(runs, first, p, inten, range_m, t_off, ground_z):  # pragma: no cover
    """The per-segment sums of :func:`segment_attributes` over the runs of
    :func:`_segment_runs`, the pixels flattened: p (N, 3) float points; inten, range_m,
    ground_z (N,) float; t_off (N,) int.

    Returns per segment (K,): ``n`` int64 pixel count, ``c`` (K, 3) float64 centroid,
    ``cov`` (K, 3, 3) float64 mean product of the offsets from the centroid, ``z0, z1``
    lowest / highest z (0 without pixels), ``g_n`` int64 pixels with a finite ground height
    and ``g_sum`` their sum, ``i_sum`` the summed intensity (``np.nan_to_num``), ``r_min``
    the nearest range (inf without pixels) and ``t_sum`` the summed time offsets (as
    float64). Each sum adds the pixels in flat order in float64, as the reference's
    ``bincount`` does; a minimum or maximum is NaN if one of its values is, as the
    reference's ``np.minimum.reduceat``.
    """
    K = first.shape[0] - 1
    n = np.zeros(K, np.int64)
    c = np.zeros((K, 3))
    cov = np.zeros((K, 3, 3))
    z0 = np.zeros(K)
    z1 = np.zeros(K)
    g_n = np.zeros(K, np.int64)
    g_sum = np.zeros(K)
    i_sum = np.zeros(K)
    r_min = np.full(K, np.inf)
    t_sum = np.zeros(K)
    big = np.finfo(np.float64).max
    for s in range(K):
        m = 0
        sx = sy = sz = 0.0
        lo, hi = np.inf, -np.inf
        gn = 0
        gs = si = st = 0.0
        rm = np.inf
        # NaN noted on the side, so the minima and maxima are plain selects (no branch
        # per pixel); the unknown ground, which comes and goes with the column, a select too
        nan_z = nan_r = False
        for r in range(first[s], first[s + 1]):
            m += runs[r, 1] - runs[r, 0]
            for i in range(runs[r, 0], runs[r, 1]):
                x = np.float64(p[i, 0])
                y = np.float64(p[i, 1])
                z = np.float64(p[i, 2])
                sx += x
                sy += y
                sz += z
                lo = z if z < lo else lo
                hi = z if z > hi else hi
                nan_z |= z != z
                g = np.float64(ground_z[i])
                fin = np.isfinite(g)
                gn += 1 if fin else 0
                # + 0.0 leaves the sum as it is (it would change only -0.0, which a sum
                # from 0.0 never is)
                gs += g if fin else 0.0
                v = np.float64(inten[i])
                if v - v != 0.0:  # NaN or infinite (rare): np.nan_to_num
                    v = 0.0 if v != v else (big if v > 0.0 else -big)
                si += v
                q = np.float64(range_m[i])
                rm = q if q < rm else rm
                nan_r |= q != q
                st += np.float64(t_off[i])
        if m == 0:
            continue
        n[s] = m
        cx, cy, cz = sx / m, sy / m, sz / m
        c[s, 0], c[s, 1], c[s, 2] = cx, cy, cz
        z0[s], z1[s] = (np.nan, np.nan) if nan_z else (lo, hi)
        r_min[s] = np.nan if nan_r else rm
        g_n[s], g_sum[s], i_sum[s], t_sum[s] = gn, gs, si, st
        # second pass: products of the offsets from the centroid (as the reference, rather
        # than raw second moments less the squared mean, which lose digits far from the
        # origin)
        xx = xy = xz = yy = yz = zz = 0.0
        for r in range(first[s], first[s + 1]):
            for i in range(runs[r, 0], runs[r, 1]):
                dx = np.float64(p[i, 0]) - cx
                dy = np.float64(p[i, 1]) - cy
                dz = np.float64(p[i, 2]) - cz
                xx += dx * dx
                xy += dx * dy
                xz += dx * dz
                yy += dy * dy
                yz += dy * dz
                zz += dz * dz
        cov[s, 0, 0] = xx / m
        cov[s, 0, 1] = cov[s, 1, 0] = xy / m
        cov[s, 0, 2] = cov[s, 2, 0] = xz / m
        cov[s, 1, 1] = yy / m
        cov[s, 1, 2] = cov[s, 2, 1] = yz / m
        cov[s, 2, 2] = zz / m
    return n, c, cov, z0, z1, g_n, g_sum, i_sum, r_min, t_sum


@numba.njit(cache=True, nogil=True)
def _segment_box(runs, first, p, c, cos, sin, z0, z1, g_n, g_sum):  # pragma: no cover
    """The oriented footprint box of each segment: its extents along (u) and across (v) the
    yaw from the centroid, then the box as ``segment_attributes_reference`` builds it.

    runs, first as :func:`_segment_runs`; p (N, 3) float points; c (K, 3) centroids; cos,
    sin (K,) of the yaws; z0, z1, g_n, g_sum (K,) as :func:`_segment_sums`. Returns
    ``center`` (K, 3), ``length, width, height, gz, clearance, area, volume`` (K,) float64
    (the fields of :class:`SegmentAttributes`); the extents are 0 for a segment without
    pixels and NaN where an offset is NaN (as ``np.minimum.reduceat``). Every expression is
    the reference's term for term and in its order: numba's default (not fastmath) code
    neither reorders nor fuses them into multiply-adds, so they round as numpy's do.
    Computing the box here rather than in numpy saves some twenty numpy calls on (K,)
    arrays (a microsecond each).
    """
    K = first.shape[0] - 1
    center = np.empty((K, 3))
    length = np.empty(K)
    width = np.empty(K)
    height = np.empty(K)
    gz = np.empty(K)
    clearance = np.empty(K)
    area = np.empty(K)
    volume = np.empty(K)
    for s in range(K):
        cx, cy, cs, sn = c[s, 0], c[s, 1], cos[s], sin[s]
        u0, u1, v0, v1 = 0.0, 0.0, 0.0, 0.0
        if first[s] < first[s + 1]:
            u0, u1, v0, v1 = np.inf, -np.inf, np.inf, -np.inf
            # NaN noted on the side, so the minima and maxima are plain selects
            bad = False
            for r in range(first[s], first[s + 1]):
                for i in range(runs[r, 0], runs[r, 1]):
                    dx = np.float64(p[i, 0]) - cx
                    dy = np.float64(p[i, 1]) - cy
                    u = dx * cs + dy * sn
                    v = -dx * sn + dy * cs
                    u0 = u if u < u0 else u0
                    u1 = u if u > u1 else u1
                    v0 = v if v < v0 else v0
                    v1 = v if v > v1 else v1
                    bad |= (u != u) | (v != v)
            if bad:
                u0 = u1 = v0 = v1 = np.nan
        g = z0[s]
        if g_n[s] > 0:
            g = _minimum(g_sum[s] / g_n[s], z0[s])
        lg, wd, ht = u1 - u0, v1 - v0, z1[s] - g
        uc, vc = (u0 + u1) / 2, (v0 + v1) / 2
        center[s, 0] = cx + uc * cs - vc * sn
        center[s, 1] = cy + uc * sn + vc * cs
        center[s, 2] = g + ht / 2
        length[s], width[s], height[s], gz[s] = lg, wd, ht, g
        clearance[s] = z0[s] - g
        area[s] = lg * wd
        volume[s] = lg * wd * ht
    return center, length, width, height, gz, clearance, area, volume


def ground_plane(
    xyz_w: np.ndarray, ground: np.ndarray, centre_xyz: np.ndarray, radius_m: float
) -> tuple[np.ndarray, float, int] | None:
    """The plane ``z = a x + b y + c`` through the ground pixels ``ground`` (H, W) bool of
    ``xyz_w`` (H, W, 3) world metres within ``radius_m`` (horizontal) of ``centre_xyz`` (3,),
    in coordinates centred there (small numbers): least squares by its 3 x 3 normal equations
    (the sums in one compiled pass over the pixels, ``ground_plane_reference`` is the
    numpy form). Returns ``((a, b, c), rms residual m, n points)``, or None under 10 points."""
    c = np.asarray(centre_xyz, dtype=np.float64)
    sums = np.zeros(10)
    _plane_sums(np.ascontiguousarray(xyz_w, dtype=np.float64), ground, c, radius_m**2, sums)
    n = int(sums[9])
    if n < 10:
        return None
    xx, xy, yy, xz, yz, zz, sx, sy, sz = sums[:9]
    AtA = np.array([[xx, xy, sx], [xy, yy, sy], [sx, sy, n]])
    coef, *_ = np.linalg.lstsq(AtA, np.array([xz, yz, sz]), rcond=None)
    a, b, k = coef
    # sum of squared residuals from the same sums: (z - a x - b y - k)^2 expanded
    ss = (
        zz + a * a * xx + b * b * yy + k * k * n
        - 2 * a * xz - 2 * b * yz - 2 * k * sz + 2 * a * b * xy + 2 * a * k * sx + 2 * b * k * sy
    )  # fmt: skip
    return coef, float(np.sqrt(max(ss, 0.0) / n)), n


@numba.njit(cache=True, nogil=True)
def _plane_sums(xyz, mask, c, r2, out):  # pragma: no cover
    """out = (xx, xy, yy, xz, yz, zz, x, y, z, n) over masked points within r2 of c (x, y)."""
    H, W = mask.shape
    for i in range(H):
        for j in range(W):
            if not mask[i, j]:
                continue
            x = xyz[i, j, 0] - c[0]
            y = xyz[i, j, 1] - c[1]
            if not x * x + y * y < r2:
                continue
            z = xyz[i, j, 2] - c[2]
            out[0] += x * x
            out[1] += x * y
            out[2] += y * y
            out[3] += x * z
            out[4] += y * z
            out[5] += z * z
            out[6] += x
            out[7] += y
            out[8] += z
            out[9] += 1.0

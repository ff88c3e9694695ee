"""Egosphere images: a LADAR sweep as a range image on the sensor egosphere (level 1 of SP).

Reference 001, 4.4.4 (Images: "the signal from each pixel in a LADAR range image may ... list
several ranges corresponding to multiple returns"), 4.4.6 (Image Field of View: the sensor,
body and inertial egospheres, "each pixel has a unique azimuth and elevation").

Pixel grid (sensor egosphere, sensor frame x forward, y left, z up):

* row ``i``: the beam (``ring``) when the sensor gives one, else the elevation bin; row 0 is the
  highest elevation (the image is upright).
* column ``j``: azimuth bin; azimuth ``atan2(y, x)`` falls from +pi at column 0 to -pi at the
  last column, so the view ahead (azimuth 0) sits in the middle and left is left.
* layer ``k``: the k-th nearest return that fell in the pixel (``max_returns`` kept).

Every pixel keeps the index of its point in the sweep and its exact ``xyz``, so back-projection
returns the original points bit for bit; the pixel's own ray (its bin centre) is available too.

:func:`to_egosphere` bins the points and keeps each pixel's nearest returns in compiled passes
(numba) around numpy's ``arctan2``; ``to_egosphere_reference`` (a test oracle, in
``tests/kernel_reference``) is the numpy form it is tested against (the same images, bit for bit).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numba
import numpy as np

from core.errors import EngineError
from core.geometry import check_pose, se3, transform_points
from logs.types import LadarScan


class EgosphereError(EngineError, ValueError):
    """A scan, configuration or transform the egosphere cannot use; names the value."""


@dataclass(frozen=True)
class EgosphereConfig:
    """Geometry of a sensor-egosphere image.

    n_rows, n_cols:     image size (beams x azimuth bins).
    elevation_min_deg, elevation_max_deg: elevation span binned into rows when the scan has no
                        ``ring`` (or ``use_ring`` is False); points outside it are dropped.
    use_ring:           take the row from the scan's beam index when present.
    ring_zero_at_bottom: beam 0 is the lowest beam (Velodyne, the simulator); else the highest.
    max_returns:        returns kept per pixel, nearest first.
    min_range_m:        closer points (the vehicle itself) are dropped.
    """

    n_rows: int = 64
    n_cols: int = 2048
    elevation_min_deg: float = -25.0
    elevation_max_deg: float = 3.0
    use_ring: bool = True
    ring_zero_at_bottom: bool = True
    max_returns: int = 2
    min_range_m: float = 0.5

    def __post_init__(self) -> None:
        if self.n_rows < 1 or self.n_cols < 1 or self.max_returns < 1:
            raise EgosphereError(
                f"egosphere needs n_rows, n_cols, max_returns >= 1, got "
                f"{self.n_rows}, {self.n_cols}, {self.max_returns}"
            )
        if not self.elevation_max_deg > self.elevation_min_deg:
            raise EgosphereError(
                f"elevation_max_deg {self.elevation_max_deg} must exceed "
                f"elevation_min_deg {self.elevation_min_deg}"
            )


class EgosphereImage:
    """A range image on the sensor egosphere; arrays are (n_rows, n_cols, max_returns[, 3]).

    range_m:      float32 metres from the sensor origin, NaN where empty.
    point_index:  int32 index of the point in the sweep, -1 where empty.
    valid:        bool, ``point_index >= 0``.
    intensity:    float32 sensor units, NaN where empty.
    xyz:          float32 metres, sensor frame, NaN where empty.
    t_offset_ns:  int64 point time minus ``t_ns``, 0 where empty.
    T_body_sensor: (4, 4) float64 sensor mount, for transforms to the body and beyond.

    Projection computes ``point_index`` and ``range_m``; the other attributes are gathered from
    the sweep on first use (most consumers need only some of them) and then kept.
    """

    def __init__(
        self,
        scan: LadarScan,
        config: EgosphereConfig,
        point_index: np.ndarray,
        range_m: np.ndarray,
        T_body_sensor: np.ndarray,
        n_dropped: int,
        n_overflow: int = 0,
    ) -> None:
        self.t_ns = int(scan.t_ns)
        self.frame_id = scan.frame_id
        self.config = config
        self.point_index = point_index
        self.range_m = range_m
        self.T_body_sensor = T_body_sensor
        self.n_dropped = n_dropped  # points outside the elevation span or nearer than min_range
        self.n_overflow = n_overflow  # points beyond max_returns in their pixel (not kept)
        self._scan = scan
        self._cache: dict[str, np.ndarray] = {}

    def _gather(self, name: str, values: np.ndarray, empty: float | int) -> np.ndarray:
        if name not in self._cache:
            v = np.asarray(values)
            at = self.valid
            if len(v):
                out = np.take(v, np.where(at, self.point_index, 0), axis=0)  # one gather
                out[~at] = empty
            else:  # a scan without points: every pixel empty
                out = np.full(self.point_index.shape + v.shape[1:], empty, dtype=v.dtype)
            self._cache[name] = out
        return self._cache[name]

    @property
    def valid(self) -> np.ndarray:
        if "valid" not in self._cache:
            self._cache["valid"] = self.point_index >= 0
        return self._cache["valid"]

    @property
    def intensity(self) -> np.ndarray:
        return self._gather("intensity", self._scan.intensity.astype(np.float32), np.nan)

    @property
    def scan_points(self) -> np.ndarray:
        """(N, 3) float32 C-order: the sweep's points in the sensor frame, as
        ``point_index`` numbers them."""
        if "scan_points" not in self._cache:
            pts = np.ascontiguousarray(self._scan.points_xyz, dtype=np.float32)
            self._cache["scan_points"] = pts.reshape(-1, 3)
        return self._cache["scan_points"]

    @property
    def xyz(self) -> np.ndarray:
        return self._gather("xyz", self._scan.points_xyz.astype(np.float32), np.nan)

    @property
    def t_offset_ns(self) -> np.ndarray:
        return self._gather("t_offset_ns", self._scan.t_offset_ns.astype(np.int64), 0)

    @property
    def range_first(self) -> np.ndarray:
        """(n_rows, n_cols) float32 nearest range per pixel, NaN where empty."""
        return self.range_m[..., 0]

    @property
    def valid_first(self) -> np.ndarray:
        """(n_rows, n_cols) bool: the pixel has at least one return."""
        return self.valid[..., 0]

    def back_project(self, T_target_sensor: np.ndarray | None = None) -> np.ndarray:
        """All returns as (M, 3) float32 points (in ``T_target_sensor``'s target frame if given),
        in sweep order, i.e. exactly the points that went in (minus the dropped ones)."""
        index = np.sort(self.point_index[self.valid])
        pts = np.asarray(self._scan.points_xyz, dtype=np.float32)[index]
        if T_target_sensor is None:
            return pts
        return transform_points(check_pose(T_target_sensor, "T_target_sensor"), pts)

    def pixel_rays(self) -> np.ndarray:
        """(n_rows, n_cols, 3) float64 unit rays through each pixel's bin centre, sensor frame
        (rows binned by elevation span; for ring rows this is the nominal beam direction)."""
        el, az = pixel_angles(self.config)
        E, A = np.meshgrid(el, az, indexing="ij")
        return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)


def pixel_angles(config: EgosphereConfig) -> tuple[np.ndarray, np.ndarray]:
    """Elevation (n_rows,) and azimuth (n_cols,) of the bin centres, radians."""
    el_lo, el_hi = np.deg2rad(config.elevation_min_deg), np.deg2rad(config.elevation_max_deg)
    el = el_hi - (np.arange(config.n_rows) + 0.5) * (el_hi - el_lo) / config.n_rows
    az = np.pi - (np.arange(config.n_cols) + 0.5) * (2 * np.pi / config.n_cols)
    return el, az


def spherical(points_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, azimuth ``atan2(y, x)`` and elevation ``atan2(z, hypot(x, y))`` of (N, 3)
    points, each (N,) float32 (metres, radians)."""
    x, y, z = points_xyz[:, 0], points_xyz[:, 1], points_xyz[:, 2]
    horiz2 = x * x + y * y
    range_m = np.sqrt(horiz2 + z * z)
    return range_m, np.arctan2(y, x), np.arctan2(z, np.sqrt(horiz2))


def check_scan(scan: LadarScan) -> None:
    """Refuse a scan whose arrays do not match :class:`~logs.types.LadarScan`."""
    pts = np.asarray(scan.points_xyz)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise EgosphereError(f"scan at t_ns={scan.t_ns}: points_xyz shape {pts.shape}, not (N, 3)")
    n = pts.shape[0]
    for name in ("intensity", "t_offset_ns"):
        a = np.asarray(getattr(scan, name))
        if a.shape != (n,):
            raise EgosphereError(f"scan at t_ns={scan.t_ns}: {name} shape {a.shape}, not ({n},)")
    if scan.ring is not None and np.asarray(scan.ring).shape != (n,):
        raise EgosphereError(f"scan at t_ns={scan.t_ns}: ring shape {scan.ring.shape}, not ({n},)")


def to_egosphere(
    scan: LadarScan,
    config: EgosphereConfig | None = None,
    T_body_sensor: np.ndarray | None = None,
) -> EgosphereImage:
    """Project a LADAR sweep to its sensor-egosphere image (nearest ``max_returns`` per pixel).

    An empty scan gives an all-empty image (callers skip it by ``valid.any()``); a malformed
    one raises :class:`EgosphereError`.

    Compiled passes over the points around numpy's ``arctan2``; the image is that of
    ``to_egosphere_reference`` bit for bit (every point lands in the same pixel by the same
    float32 arithmetic, and a pixel's returns are ordered by the same (range, index) key).
    """
    cfg = config or EgosphereConfig()
    check_scan(scan)
    pts = np.asarray(scan.points_xyz, dtype=np.float32)
    n = pts.shape[0]
    use_ring = cfg.use_ring and scan.ring is not None
    work = _WORK
    point_range_m = work.array("point_range_m", n, np.float32)
    yx = work.array("yx", 2 * n, np.float32).reshape(2, n)
    zh = work.array("zh", 0 if use_ring else 2 * n, np.float32).reshape(2, -1)
    # flat (N * 3,): a 1-D C array is what numba vectorizes (2-D indexing stays scalar)
    _spherical_kernel(
        np.ascontiguousarray(pts).reshape(-1), point_range_m, yx[0], yx[1], zh[0], zh[1]
    )
    # The angles come from numpy's arctan2, the reference's own: on AVX-512 machines it is a
    # SIMD routine that differs from libm's atan2f (what the kernel would call) by an ulp for
    # many points, enough to move a point across a bin edge, and it is much faster than
    # atan2f in a loop. It is element-wise, so contiguous inputs give the values of the
    # reference's strided views, and read faster.
    az = np.arctan2(yx[0], yx[1], out=work.array("az", n, np.float32))
    if use_ring:
        el = np.empty(0, dtype=np.float32)
        ring = np.asarray(scan.ring)
        if ring.dtype != np.uint16:  # the sensors' dtype is read as is, others as the reference
            ring = ring.astype(np.int32)
    else:
        el = np.arctan2(zh[0], zh[1], out=work.array("el", n, np.float32))
        ring = np.empty(0, dtype=np.uint16)
    # The constants as the reference's numpy expressions make them: a point's pixel is decided
    # in float32, and numpy compares the float32 ranges with min_range_m cast to float32.
    el_hi = np.float32(np.deg2rad(cfg.elevation_max_deg))
    el_scale = np.float32(cfg.n_rows / (el_hi - np.deg2rad(cfg.elevation_min_deg)))
    col_scale = np.float32(cfg.n_cols / (2 * np.pi))
    K, n_pix = cfg.max_returns, cfg.n_rows * cfg.n_cols
    # (K, pixels) as the reference builds them, so the returned arrays are the same views.
    index = np.empty((K, n_pix), dtype=np.int32)
    range_m = np.empty((K, n_pix), dtype=np.float32)
    filled = np.empty(K, dtype=np.int64)
    pix = work.array("pix", n, np.int64)
    keys = work.array("keys", K * cfg.n_rows * (cfg.n_cols + _PAD), np.uint64)
    n_ok = _nearest_kernel(
        az, el, ring, point_range_m, use_ring, cfg.ring_zero_at_bottom, cfg.n_rows, cfg.n_cols,
        np.float32(np.pi), col_scale, el_hi, el_scale, np.float32(cfg.min_range_m), pix, keys,
        index.reshape(-1).view(np.uint32), range_m.reshape(-1).view(np.uint32), filled,
    )  # fmt: skip
    # The reference stops once every point is placed: its later layers keep np.nan's bits
    # (an empty pixel of a layer it computed has the NaN 0xFFFFFFFF, as here).
    placed = 0
    for k in range(1, K):
        placed += int(filled[k - 1])
        if placed == n_ok:
            range_m[k:] = np.nan
            break
    n_overflow = n_ok - int(filled.sum())
    # (K, rows, cols) seen as (rows, cols, K): the reference's np.moveaxis(a, 0, -1) views
    index = index.reshape(K, cfg.n_rows, cfg.n_cols).transpose(1, 2, 0)
    range_m = range_m.reshape(K, cfg.n_rows, cfg.n_cols).transpose(1, 2, 0)
    T = np.eye(4) if T_body_sensor is None else check_pose(T_body_sensor, "T_body_sensor")
    return EgosphereImage(scan, cfg, index, range_m, T, n - n_ok, n_overflow)


class _Work(threading.local):
    """Work arrays of :func:`to_egosphere`, one set per thread (the kernels release the GIL),
    kept at the size of the largest sweep seen and reused. Fresh ones each call are megabytes
    that malloc may give back to the system when they are freed (a trimmed heap), and then
    every call page-faults them in again, which costs more than the projection itself."""

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def array(self, name: str, size: int, dtype: type) -> np.ndarray:
        """The first ``size`` entries of the work array ``name`` (1-D C, contents undefined)."""
        a = self.arrays.get(name)
        if a is None or a.size < size:
            a = self.arrays[name] = np.empty(size, dtype=dtype)
        return a[:size]


_WORK = _Work()


@numba.njit(cache=True, nogil=True)
def _spherical_kernel(xyz, range_m, y, x, z, horiz):  # pragma: no cover
    """xyz (N * 3,) float32 metres, the points' coordinates in a row. Fills range_m (N,) float32
    the range ``sqrt(x^2 + y^2 + z^2)``, y and x (N,) float32 each point's y and x (contiguous
    for ``arctan2``) and, unless they are empty, z and horiz (N,) float32 its z and
    ``sqrt(x^2 + y^2)``.

    Float32 operations in the reference's order (numba contracts no multiply-add into an FMA
    without fastmath), so every value is the reference's to the bit."""
    n = range_m.shape[0]
    if z.shape[0] == n and n:
        for i in range(n):
            xi = xyz[3 * i]
            yi = xyz[3 * i + 1]
            zi = xyz[3 * i + 2]
            horiz2 = xi * xi + yi * yi
            range_m[i] = np.sqrt(horiz2 + zi * zi)
            y[i] = yi
            x[i] = xi
            z[i] = zi
            horiz[i] = np.sqrt(horiz2)
    else:
        for i in range(n):
            xi = xyz[3 * i]
            yi = xyz[3 * i + 1]
            zi = xyz[3 * i + 2]
            range_m[i] = np.sqrt(xi * xi + yi * yi + zi * zi)
            y[i] = yi
            x[i] = xi


# Row padding of the key scratch, in pixels: a sweep comes column by column, so consecutive
# points fall a row apart, and with a power-of-two row (1024 pixels) every one of them would
# hit the same cache set and alias the previous stores (4K aliasing), which stalls the loop.
_PAD = 8


@numba.njit(cache=True, nogil=True)
def _nearest_kernel(  # pragma: no cover
    az, el, ring, point_range_m, use_ring, ring_zero_at_bottom, n_rows, n_cols,
    pi, col_scale, el_hi, el_scale, min_range, pix, keys, index, range_bits, filled,
):  # fmt: skip
    """The pixel of every point as :func:`_pixel_of` finds it, and each pixel's nearest returns.

    az, el (N,) float32 radians (el unused, may be empty, with ``use_ring``); ring (N,) uint16 or
    int32 beam (empty without ``use_ring``); point_range_m (N,) float32 metres; the float32
    constants as :func:`to_egosphere` makes them; pix (N,) int64 and keys
    (K * n_rows * (n_cols + _PAD),) uint64 work arrays (overwritten). Fills index
    (K * n_rows * n_cols,) uint32 (the int32 point index, all ones for none) and range_bits (same
    shape) uint32 (the float32 range, all ones for none), layer by layer, with each pixel's returns
    nearest first, and filled (K,) int64 with the number of pixels with a k-th return. Returns the
    number of points kept (not dropped).

    A pixel's returns are the K least of the reference's keys, (range bits, point index) in a
    uint64, so ties in range break to the lower index as there."""
    n = point_range_m.shape[0]
    K = filled.shape[0]
    w = n_cols + _PAD  # a row of the scratch
    L = n_rows * w  # a layer of the scratch
    # 1. each point's pixel in the scratch, -1 if dropped (no branches: this loop vectorizes)
    n_ok = 0
    if use_ring:
        top = n_rows - 1 if ring_zero_at_bottom else 0
        step = -1 if ring_zero_at_bottom else 1
        for i in range(n):
            row = top + step * np.int64(ring[i])
            col = np.int64(np.int32((pi - az[i]) * col_scale))  # truncation, as astype
            col = min(max(col, 0), n_cols - 1)
            # NaN points fail the range test (every other point has numbers for angles)
            ok = (point_range_m[i] >= min_range) & (row >= 0) & (row < n_rows)
            pix[i] = row * w + col if ok else -1
            n_ok += ok
    else:
        for i in range(n):
            row_f = (el_hi - el[i]) * el_scale
            row = np.int64(np.int32(row_f))  # used only where row_f is in [0, n_rows)
            col = np.int64(np.int32((pi - az[i]) * col_scale))
            col = min(max(col, 0), n_cols - 1)
            ok = (point_range_m[i] >= min_range) & (row_f >= 0) & (row_f < n_rows)
            pix[i] = row * w + col if ok else -1
            n_ok += ok
    # 2. the K least keys of each pixel, in layers of the scratch
    none = np.uint64(0xFFFFFFFFFFFFFFFF)  # an empty slot: reads as index -1 and a NaN range
    keys[:] = none
    bits = point_range_m.view(np.uint32)
    for i in range(n):
        p = pix[i]
        if p < 0:
            continue
        key = (np.uint64(bits[i]) << np.uint64(32)) | np.uint64(i)
        if K == 1:
            keys[p] = min(keys[p], key)
        elif keys[p] == none:  # the first return of its pixel: most points of a sweep
            keys[p] = key
        elif key < keys[(K - 1) * L + p]:  # insertion into the pixel's sorted keys
            t = K - 1
            while t > 0 and keys[(t - 1) * L + p] > key:
                keys[t * L + p] = keys[(t - 1) * L + p]
                t -= 1
            keys[t * L + p] = key
    # 3. the keys' halves to the image, row by row (slices, so that the copy vectorizes)
    low = np.uint64(0xFFFFFFFF)
    n_pix = n_rows * n_cols
    for k in range(K):
        count = 0
        for r in range(n_rows):
            src = keys[k * L + r * w : k * L + r * w + n_cols]
            out_index = index[k * n_pix + r * n_cols : k * n_pix + (r + 1) * n_cols]
            out_range = range_bits[k * n_pix + r * n_cols : k * n_pix + (r + 1) * n_cols]
            for c in range(n_cols):
                key = src[c]
                out_index[c] = np.uint32(key & low)
                out_range[c] = np.uint32(key >> np.uint64(32))
                count += key != none
        filled[k] = count
    return n_ok


def T_inertial_body(T_world_body: np.ndarray) -> np.ndarray:
    """Body pose in the inertial egosphere frame (4.4.6): centred on the body, axes parallel to
    the world's (gravity defines the poles, world x the zero azimuth), so only rotation."""
    return se3(check_pose(T_world_body, "T_world_body")[:3, :3])


def T_world_inertial(T_world_body: np.ndarray) -> np.ndarray:
    """The inertial egosphere's pose in the world: a translation to the body origin."""
    return se3(t=check_pose(T_world_body, "T_world_body")[:3, 3])


def egosphere_points(
    image: EgosphereImage, T_world_body: np.ndarray, frame: str = "world"
) -> np.ndarray:
    """Back-projected returns (M, 3) float32 in ``frame``: "sensor", "body", "inertial" or
    "world" (the inertial egosphere is the body origin with world-aligned axes)."""
    T_body_sensor = image.T_body_sensor
    if frame == "sensor":
        return image.back_project()
    if frame == "body":
        return image.back_project(T_body_sensor)
    if frame == "inertial":
        return image.back_project(T_inertial_body(T_world_body) @ T_body_sensor)
    if frame == "world":
        return image.back_project(check_pose(T_world_body, "T_world_body") @ T_body_sensor)
    raise EgosphereError(f"unknown frame {frame!r}: use sensor, body, inertial or world")

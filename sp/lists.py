"""Level 2 of SP: list entities (edges, vertices, surface patches) on the egosphere image.

Reference 001, 4.5.6 "Level 2 Regions: List entities and events": a group of pixels with
contiguous range or brightness gradients is an edge, "vertices of various kinds" (T, Y, V or
line-end) are where edges meet or end, and a surface patch is a small group of pixels with
similar range and orientation (attributes: area, texture, average range, average surface
gradient, average colour). Level 3 groups the patches into surfaces ("a set of contiguous
surface patch list entities with similar range and motion", same section, Level 3 Grouping).

The pixel-level primitives live here, as numpy / OpenCV over the whole image at once, or as
compiled passes:

* :func:`range_jump_edges` (for :func:`sp.segments.range_edges`): the nearer side of every
  range jump to a row or column neighbour;
* :func:`brightness_edges`: Canny (OpenCV) on the LADAR intensity image, masked to pixels
  whose 3x3 neighbourhood is all valid (an edge of the valid region is not a brightness edge);
* :func:`edge_branches`: the crossing number of each edge pixel (how many edge branches leave
  it: 1 a line end, 2 inside an edge, 3 a T or Y, 4 and more a cross), from which vertices;
* :func:`patch_grid`: a plane fitted to the pixels of each block of a coarse grid (``rows x
  cols`` pixels), with its normal, roughness, centroid and extent;
* :func:`list_slots` (with :func:`list_slots_and_sums`): the (owner, kind) list of every
  pixel, and :func:`list_sums` then :func:`list_attributes`: attributes integrated over the
  pixels of each list entity.

:func:`range_jump_edges`, :func:`brightness_edges`, :func:`block_moments`, :func:`list_slots`
(and its fused form) and :func:`list_sums` are compiled single passes over the image (numba;
compiled on first call, cached on disk). :func:`range_jump_edges_reference` stays here, the
numpy form :func:`range_jump_edges` falls back to for dtypes it was not compiled for; the
numpy forms of the others are test oracles (``tests/kernel_reference/lists_reference.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import cv2
import numba
import numpy as np

from core.errors import EngineError


class ListError(EngineError, ValueError):
    """An image, mask or grid of the wrong shape or size; names it."""


class ListKind(IntEnum):
    """Kinds of list entity; the value is the slot in the per-owner table."""

    RANGE_EDGE = 0
    BRIGHTNESS_EDGE = 1
    VERTEX = 2
    SURFACE_PATCH = 3


KIND_CLASS = {
    ListKind.RANGE_EDGE: "range_edge",
    ListKind.BRIGHTNESS_EDGE: "brightness_edge",
    ListKind.VERTEX: "vertex",
    ListKind.SURFACE_PATCH: "surface_patch",
}


@dataclass(frozen=True)
class ListConfig:
    """canny_low, canny_high: Canny thresholds on the intensity image scaled so that its mean
    valid intensity is 100 (so a step of half the mean brightness is 50 grey levels);
    patch_rows, patch_cols: block size of the patch grid (pixels); min_patch_pixels: fewer valid
    pixels in a block make no patch; max_patch_roughness_m: a block whose points scatter more
    than this off their plane is no patch (clutter, foliage)."""

    canny_low: float = 40.0
    canny_high: float = 80.0
    patch_rows: int = 4
    patch_cols: int = 16
    min_patch_pixels: int = 8
    max_patch_roughness_m: float = 0.15


def mean_intensity(intensity: np.ndarray, valid: np.ndarray) -> float:
    """Mean of ``intensity`` over the ``valid`` pixels (1.0 when there are none)."""
    n = int(np.count_nonzero(valid))
    return float(np.where(valid, intensity, 0.0).sum(dtype=np.float64)) / n if n else 1.0


def brightness_edges(
    intensity: np.ndarray,
    valid: np.ndarray,
    config: ListConfig | None = None,
    mean: float | None = None,
) -> np.ndarray:
    """(H, W) bool pixels on a brightness edge of ``intensity`` ((H, W) sensor units, NaN or
    any value where not ``valid``). Intensity is scaled by ``mean``, its mean over the valid
    pixels (:func:`mean_intensity`, computed when not given), so the thresholds are relative
    (a reflectance step, whatever the sensor's units)."""
    cfg = config or ListConfig()
    if intensity.shape != valid.shape or intensity.ndim != 2:
        raise ListError(f"intensity {intensity.shape} and valid {valid.shape} must be one (H, W)")
    mean = mean_intensity(intensity, valid) if mean is None else mean
    if not mean > 0.0 or not valid.any():
        return np.zeros(valid.shape, dtype=bool)
    # |x| scaled and saturated to 0..255; NaN becomes 0, and the erosion below drops every
    # pixel next to an invalid one, whatever its value there
    img8 = cv2.convertScaleAbs(np.asarray(intensity, dtype=np.float32), alpha=100.0 / mean)
    edge = cv2.Canny(img8, cfg.canny_low, cfg.canny_high, L2gradient=True) > 0
    inner = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0) > 0
    return edge & inner


def range_jump_edges_reference(
    range_m: np.ndarray, valid: np.ndarray, jump_m: float, jump_frac: float
) -> np.ndarray:
    """Reference of :func:`range_jump_edges` in plain numpy (``np.roll`` per axis); ``valid``
    is broadcast against ``range_m`` and any dtypes are taken, as numpy takes them."""
    r = np.where(valid, range_m, np.inf)
    edge = np.zeros(valid.shape, dtype=bool)
    for axis in (0, 1):
        nxt = np.roll(r, -1, axis=axis)
        if axis == 0:
            nxt[-1] = r[-1]  # the image's bottom border is no edge
        lo = np.minimum(r, nxt)
        with np.errstate(invalid="ignore"):
            jump = np.abs(r - nxt) > jump_m + jump_frac * lo
        jump &= np.isfinite(lo)
        near_here = jump & (r <= nxt)
        near_next = jump & (nxt < r)
        edge |= near_here
        edge |= np.roll(near_next, 1, axis=axis) & (
            np.ones_like(edge) if axis == 1 else np.arange(edge.shape[0])[:, None] > 0
        )
    return edge & valid


@numba.njit(cache=True, nogil=True, inline="always")
def _jump(a, b, jump_m, jump_frac):  # pragma: no cover
    """The reference's jump test of one pair of ranges, all in one float dtype:
    ``|a - b| > jump_m + jump_frac * min(a, b)`` with the smaller range finite. A NaN on
    either side is no jump, as in the reference (where np.minimum makes ``lo`` NaN): here
    ``lo`` may be the other range, but ``|a - b|`` is NaN and compares false. Without
    branches (``&`` not ``and``): the jumps of a noisy sweep are too many to predict."""
    lo = a if a <= b else b
    return np.isfinite(lo) & (abs(a - b) > jump_m + jump_frac * lo)


@numba.njit(cache=True, nogil=True)
def _range_jump_edges_kernel(range_m, valid, inf, jump_m, jump_frac, edge):  # pragma: no cover
    """Fills ``edge`` ((H, W) bool) with the nearer side of every jump to the right or left
    (azimuth wraps) and lower or upper neighbour; ``inf``, ``jump_m``, ``jump_frac`` are
    scalars of ``range_m``'s dtype, so the arithmetic is numpy's in that dtype."""
    H, W = range_m.shape
    # the ranges with invalid pixels infinitely far and a wrapped column at either side
    r = np.empty((H, W + 2), dtype=range_m.dtype)
    for i in range(H):
        for j in range(W):
            r[i, j + 1] = range_m[i, j] if valid[i, j] else inf
        if W:
            r[i, 0] = r[i, W]
            r[i, W + 1] = r[i, 1]
    for i in range(H):
        mid = r[i]
        # the top row has no pair above and the bottom row is paired with itself (as in the
        # reference); a pair with itself never makes its lower side (a < a) an edge, so the
        # top row may pair with itself too
        up = r[i - 1] if i > 0 else mid
        dn = r[i + 1] if i + 1 < H else mid
        for j in range(W):
            a = mid[j + 1]
            c, d, u, e = mid[j + 2], mid[j], up[j + 1], dn[j + 1]
            # this pixel is the nearer (or, to the right and below, the equal) side of a jump
            edge[i, j] = valid[i, j] & (
                (_jump(a, c, jump_m, jump_frac) & (a <= c))
                | (_jump(d, a, jump_m, jump_frac) & (a < d))
                | (_jump(a, e, jump_m, jump_frac) & (a <= e))
                | (_jump(u, a, jump_m, jump_frac) & (a < u))
            )


def range_jump_edges(
    range_m: np.ndarray, valid: np.ndarray, jump_m: float, jump_frac: float
) -> np.ndarray:
    """(H, W) bool level-2 range-edge pixels: the nearer side of every jump of more than
    ``jump_m + jump_frac * nearer range`` (metres) between a ``valid`` pixel and its right
    (azimuth wraps round) or lower neighbour (the nearer side is the occluding boundary; an
    invalid neighbour counts as infinitely far, so the returns round an empty pixel are
    edges; a NaN range makes no jump).
    ``range_m`` (H, W) float32 or float64 metres, ``valid`` (H, W) bool. One compiled pass,
    in ``range_m``'s dtype as numpy computes the threshold; other dtypes, shapes or
    thresholds that numpy would widen (numpy scalars) are left to
    :func:`range_jump_edges_reference`, which it equals."""
    dt = range_m.dtype
    if (
        range_m.ndim != 2
        or valid.shape != range_m.shape
        or valid.dtype != np.bool_
        or dt not in (np.float32, np.float64)
        or np.result_type(jump_m, np.result_type(jump_frac, dt)) != dt
    ):
        return range_jump_edges_reference(range_m, valid, jump_m, jump_frac)
    edge = np.empty(range_m.shape, dtype=bool)
    f = dt.type
    _range_jump_edges_kernel(
        np.ascontiguousarray(range_m),
        np.ascontiguousarray(valid),
        f(np.inf),
        f(jump_m),
        f(jump_frac),
        edge,
    )
    return edge


_RING = ((-1, -1), (-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1))


def edge_branches(edge: np.ndarray) -> np.ndarray:
    """(H, W) int8 crossing number of every edge pixel (0 off the edges): the number of
    off-to-on steps walking once round its 8 neighbours, i.e. the edge branches that leave
    the pixel (1 a line end, 2 the inside of an edge, >= 3 a junction: T, Y or X vertex).
    An isolated edge pixel has 0. Pixels beyond the image border count as off."""
    if edge.ndim != 2:
        raise ListError(f"edge image must be (H, W), got {edge.shape}")
    p = np.pad(edge, 1)
    H, W = edge.shape
    ring = [p[1 + di : 1 + di + H, 1 + dj : 1 + dj + W] for di, dj in _RING]
    n = np.zeros((H, W), dtype=np.int8)
    for a, b in zip(ring, ring[1:] + ring[:1], strict=True):
        n += ~a & b
    return np.where(edge, n, 0).astype(np.int8)


def vertices(branches: np.ndarray) -> np.ndarray:
    """(H, W) bool vertex pixels: edge ends (1 branch) and junctions (>= 3 branches)."""
    return (branches == 1) | (branches >= 3)


@dataclass
class PatchGrid:
    """A plane fitted to each block of the patch grid (B = blocks, row-major over the grid
    (n_block_rows, n_block_cols)); all in the frame of the points given (metres).

    n:          (B,) int64 pixels fitted.
    ok:         (B,) bool the block is a patch (enough pixels, planar, not rough).
    centroid:   (B, 3) float64 mean point.
    normal:     (B, 3) float64 unit normal (smallest scatter axis), pointing towards the
                sensor origin; zero for blocks with too few pixels to fit.
    roughness_m: (B,) float64 standard deviation of the points off the plane.
    z_min, z_max: (B,) float64 lowest and highest point.
    shape:      (n_block_rows, n_block_cols).
    block:      (rows, cols) pixels per block.
    """

    n: np.ndarray
    ok: np.ndarray
    centroid: np.ndarray
    normal: np.ndarray
    roughness_m: np.ndarray
    z_min: np.ndarray
    z_max: np.ndarray
    shape: tuple[int, int]
    block: tuple[int, int]

    def block_of_pixel(self, H: int, W: int) -> np.ndarray:
        """(H, W) int64 block index of every pixel."""
        bh, bw = self.block
        rows = np.arange(H) // bh
        cols = np.arange(W) // bw
        return rows[:, None] * self.shape[1] + cols[None, :]


MOMENTS = ("n", "sx", "sy", "sz", "sxx", "sxy", "sxz", "syy", "syz", "szz", "z_min", "z_max")


@numba.njit(cache=True, nogil=True)
def _block_moments_kernel(
    xyz: np.ndarray, mask: np.ndarray, bh: int, bw: int, nbc: int, out: np.ndarray
) -> None:
    H, W = mask.shape
    for i in range(H):
        row = (i // bh) * nbc
        for j in range(W):
            if not mask[i, j]:
                continue
            b = row + j // bw
            x, y, z = float(xyz[i, j, 0]), float(xyz[i, j, 1]), float(xyz[i, j, 2])
            out[b, 0] += 1.0
            out[b, 1] += x
            out[b, 2] += y
            out[b, 3] += z
            out[b, 4] += x * x
            out[b, 5] += x * y
            out[b, 6] += x * z
            out[b, 7] += y * y
            out[b, 8] += y * z
            out[b, 9] += z * z
            out[b, 10] = min(out[b, 10], z)
            out[b, 11] = max(out[b, 11], z)


def _moments_init(nbr: int, nbc: int) -> np.ndarray:
    out = np.zeros((nbr * nbc, len(MOMENTS)))
    out[:, 10] = np.inf
    out[:, 11] = -np.inf
    return out


def block_moments(xyz: np.ndarray, mask: np.ndarray, bh: int, bw: int) -> np.ndarray:
    """(B, 12) float64 sums over the ``mask`` pixels of each block of ``bh x bw`` pixels
    (B row-major over the block grid, partial blocks at the right and bottom included):
    the count, the sums of x, y, z and of their six products (:data:`MOMENTS` order), the
    lowest and highest z (inf / -inf for an empty block). One compiled pass over the image;
    ``block_moments_reference`` (a test oracle) is its numpy form."""
    H, W = mask.shape
    nbr, nbc = -(-H // bh), -(-W // bw)
    out = _moments_init(nbr, nbc)
    _block_moments_kernel(
        np.ascontiguousarray(xyz), np.ascontiguousarray(mask, dtype=np.bool_), bh, bw, nbc, out
    )
    return out


def patch_grid(xyz: np.ndarray, mask: np.ndarray, config: ListConfig | None = None) -> PatchGrid:
    """Fit a plane to the ``mask`` pixels of every block: ``xyz`` (H, W, 3) points in a frame
    whose origin is the sensor (the sensor or the gravity-aligned sensor frame, metres; the
    sums are taken there, where coordinates stay small), ``mask`` (H, W) bool. A block is a
    patch with at least ``min_patch_pixels`` pixels spread in two directions (middle scatter
    axis over 5 cm) and a roughness under ``max_patch_roughness_m``."""
    cfg = config or ListConfig()
    if xyz.shape != (*mask.shape, 3):
        raise ListError(f"xyz {xyz.shape} does not match mask {mask.shape}")
    bh, bw = cfg.patch_rows, cfg.patch_cols
    H, W = mask.shape
    m = block_moments(xyz, mask, bh, bw)
    n = m[:, 0]
    k = np.maximum(n, 1.0)
    mean = m[:, 1:4] / k[:, None]
    cov = np.empty((n.size, 3, 3))
    for (a, b), col in zip(
        ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), range(4, 10), strict=True
    ):
        cov[:, a, b] = cov[:, b, a] = m[:, col] / k - mean[:, a] * mean[:, b]
    # the scatter's axes, only where there are enough pixels for a patch
    fit = np.flatnonzero(n >= cfg.min_patch_pixels)
    w = np.zeros((n.size, 3))
    normal = np.zeros((n.size, 3))
    if fit.size:
        w[fit], v = np.linalg.eigh(cov[fit])
        normal[fit] = v[:, :, 0]
    flip = np.einsum("ij,ij->i", normal, mean) > 0.0  # point towards the sensor at the origin
    normal[flip] *= -1.0
    rough = np.sqrt(np.maximum(w[:, 0], 0.0))
    spread = np.sqrt(np.maximum(w[:, 1], 0.0))
    ok = (n >= cfg.min_patch_pixels) & (spread > 0.05) & (rough <= cfg.max_patch_roughness_m)
    return PatchGrid(
        n=n.astype(np.int64),
        ok=ok,
        centroid=mean,
        normal=normal,
        roughness_m=rough,
        z_min=m[:, 10],
        z_max=m[:, 11],
        shape=(-(-H // bh), -(-W // bw)),
        block=(bh, bw),
    )


@dataclass
class ListAttributes:
    """Attributes of L list entities integrated over their pixels (arrays (L,)).

    ids:           int64 the lists' slots (rows of the sums table, sorted); the caller
                   maps them to frame ids.
    n_pixels:      int64 pixels this sweep.
    range_m:       mean range (m).
    size_m:        pixels times their mean footprint (range x azimuth step, m): an edge's
                   length, a patch list's extent along the image.
    range_jump_m:  mean over pixels of the largest range step to a neighbour in its row (m).
    contrast:      mean over pixels of the largest intensity step to a 4-neighbour over the
                   image's mean intensity (dimensionless).
    edge_share:    share of pixels on a range or brightness edge.
    vertex_share:  share of pixels that are vertices (1 or >= 3 branches).
    branches:      mean crossing number of the pixels (vertex type: 1 end, 3 T/Y, 4 X).
    orientation_rad: direction of the pixels' principal axis in the image (0 along a row,
                   pi/2 along a column), in [0, pi).
    """

    ids: np.ndarray
    n_pixels: np.ndarray
    range_m: np.ndarray
    size_m: np.ndarray
    range_jump_m: np.ndarray
    contrast: np.ndarray
    edge_share: np.ndarray
    vertex_share: np.ndarray
    branches: np.ndarray
    orientation_rad: np.ndarray

    def as_dicts(self) -> list[dict[str, float]]:
        """One attribute dict (name -> value) per entity, for the classifier and the KD."""
        names = [
            "n_pixels", "range_m", "size_m", "range_jump_m", "contrast", "edge_share",
            "vertex_share", "branches", "orientation_rad",
        ]  # fmt: skip
        cols = [getattr(self, k).astype(np.float64) for k in names]
        return [
            dict(zip(names, (float(c[i]) for c in cols), strict=True)) for i in range(len(self.ids))
        ]


@numba.njit(cache=True, nogil=True, inline="always")
def _step(a, b, best):  # pragma: no cover
    """``|a - b|`` where it is finite and over ``best``, else ``best`` (a NaN or infinite
    step is skipped, as :func:`_accumulate` skips it), in the dtype of ``a`` and ``b``: the
    largest of such steps is the same value whichever dtype it is compared in."""
    d = abs(a - b)
    return d if (d > best) & (d < np.inf) else best


@numba.njit(cache=True, nogil=True)
def _list_slots_kernel(
    owner: np.ndarray,
    range_edge: np.ndarray,
    brightness_edge: np.ndarray,
    patch: np.ndarray,
    lut: np.ndarray,
    list_ids: np.ndarray,
    range_m: np.ndarray,
    intensity: np.ndarray,
    zero_r: float,
    zero_i: float,
    branches: np.ndarray,
    slots: np.ndarray,
    ids: np.ndarray,
    sums: np.ndarray,
) -> int:  # pragma: no cover
    """Fills ``branches``, ``slots``, ``ids`` and adds to ``sums`` (see :func:`list_slots`);
    ``zero_r`` / ``zero_i`` are 0 in the dtypes of ``range_m`` / ``intensity``. Returns the
    number of pixels left waiting for a list (slot ``-2 - key``).

    Row by row in passes that each do one thing over the row: the crossing numbers and
    kinds, the keys, the table look-ups, the list pixels' neighbour steps (passes the
    compiler turns into vector code), then the sums over the row's list pixels only, in
    pixel order as :func:`_accumulate` adds them (so the sums are the same floats), rather
    than one pixel at a time with branches: a sweep's edges, about a quarter of its pixels,
    lie too scattered for such branches to be predicted."""
    H, W = owner.shape
    n_sums = sums.shape[0]
    # the union of the edges inside a border of off pixels: every pixel's ring is read
    # without a bounds test
    on = np.zeros((H + 2, W + 2), dtype=np.uint8)
    for i in range(H):
        for j in range(W):
            on[i + 1, j + 1] = range_edge[i, j] | brightness_edge[i, j]
    # key -> slot and key -> list id, with one more entry (-1) for "no key"
    n_lut = lut.size
    slot_of = np.empty(n_lut + 1, dtype=np.int64)
    id_of = np.empty(n_lut + 1, dtype=np.int64)
    for k in range(n_lut):
        slot_of[k] = lut[k]
        id_of[k] = list_ids[lut[k]] if 0 <= lut[k] < list_ids.size else -1
    slot_of[n_lut] = -1
    id_of[n_lut] = -1
    key = np.empty(W, dtype=np.int64)
    sel = np.empty(W, dtype=np.int64)
    step_r = np.empty(W, dtype=range_m.dtype)
    step_i = np.empty(W, dtype=intensity.dtype)
    pending = 0
    for i in range(H):
        up, mid, dn = on[i], on[i + 1], on[i + 2]
        br_row, s_row, id_row = branches[i], slots[i], ids[i]
        re_row, p_row, o_row = range_edge[i], patch[i], owner[i]
        for j in range(W):
            # crossing number: off-to-on steps round the ring of _RING (upper left first,
            # clockwise), 0 off the edges
            n0, n1, n2, n3 = up[j], up[j + 1], up[j + 2], mid[j + 2]
            n4, n5, n6, n7 = dn[j + 2], dn[j + 1], dn[j], mid[j]
            e = mid[j + 1]
            br = e * (
                (1 - n0) * n1
                + (1 - n1) * n2
                + (1 - n2) * n3
                + (1 - n3) * n4
                + (1 - n4) * n5
                + (1 - n5) * n6
                + (1 - n6) * n7
                + (1 - n7) * n0
            )
            br_row[j] = br
            # kind: vertex (1 or >= 3 branches), else range edge, else brightness edge
            # (an edge off the range edges), else surface patch, else none (-1); in
            # arithmetic rather than branches
            k = np.int64(-1) + 4 * np.int64(p_row[j])
            k += np.int64(e) * (1 - k)
            k -= np.int64(re_row[j]) * k
            k += np.int64((br == 1) | (br >= 3)) * (2 - k)
            o = o_row[j]
            key[j] = o * 4 + k if (k >= 0) & (o >= 0) else -1
        n = 0
        for j in range(W):
            kj = key[j]
            x = kj if (kj >= 0) & (kj < n_lut) else n_lut
            s = slot_of[x]
            wait = (kj >= 0) & (s < 0)  # no list for this key yet: the key, encoded
            pending += wait
            s_row[j] = -2 - kj if wait else s
            id_row[j] = id_of[x]
        for j in range(W):  # the row's pixels whose list is summed, in order
            sel[n] = j
            n += (s_row[j] >= 0) & (s_row[j] < n_sums)
        if n == 0:
            continue
        # steps to the neighbours (see _accumulate): range along the row, intensity to the
        # 4-neighbours; columns wrap, rows stop at the border
        r_row, i_row = range_m[i], intensity[i]
        i_up, i_dn = intensity[max(i - 1, 0)], intensity[min(i + 1, H - 1)]
        for j in range(1, W - 1):
            r0, i0 = r_row[j], i_row[j]
            step_r[j] = _step(r_row[j - 1], r0, _step(r_row[j + 1], r0, zero_r))
            d = _step(i_row[j + 1], i0, zero_i)
            d = _step(i_row[j - 1], i0, d)
            d = _step(i_dn[j], i0, d)
            step_i[j] = _step(i_up[j], i0, d)
        for j in (0, W - 1):
            jr, jl = (j + 1) % W, (j - 1) % W
            r0, i0 = r_row[j], i_row[j]
            step_r[j] = _step(r_row[jl], r0, _step(r_row[jr], r0, zero_r))
            d = _step(i_row[jr], i0, zero_i)
            d = _step(i_row[jl], i0, d)
            d = _step(i_dn[j], i0, d)
            step_i[j] = _step(i_up[j], i0, d)
        for t in range(n):
            j = sel[t]
            s = s_row[j]
            br = br_row[j]
            r0 = r_row[j]
            sums[s, 0] += 1.0
            sums[s, 1] += r0 if abs(r0) < np.inf else 0.0
            sums[s, 2] += np.float64(step_r[j])
            sums[s, 3] += np.float64(step_i[j])
            sums[s, 4] += 1.0 if mid[j + 1] else 0.0
            sums[s, 5] += 1.0 if (br == 1 or br >= 3) else 0.0
            sums[s, 6] += br
            sums[s, 7] += i
            sums[s, 8] += j
            sums[s, 9] += i * i
            sums[s, 10] += j * j
            sums[s, 11] += i * j
    return pending


def list_slots(
    owner: np.ndarray,
    range_edge: np.ndarray,
    brightness_edge: np.ndarray,
    patch: np.ndarray,
    lut: np.ndarray,
    list_ids: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The list each pixel belongs to, in one compiled pass: its kind (a vertex where the
    edge crossing number is 1 or >= 3, else a range edge, a brightness edge, or a surface
    patch where ``patch``), the key ``owner * 4 + kind`` of its (owner, kind) list, that
    list's slot ``lut[key]`` and frame id ``list_ids[slot]``. ``owner`` (H, W) int64 (-1
    none); the three masks (H, W) bool; ``lut`` (K,) int64 key -> slot (-1 none);
    ``list_ids`` (S,) int64. Returns (slots (H, W) int64: the slot, -1 no list, ``-2 - key``
    where the key has no slot yet (:func:`fill_slots` fills them once the lists exist); list
    ids (H, W) int64 (the level-2 entity image, -1 none); branches (H, W) int8 from
    :func:`edge_branches`; the sorted keys that have no slot). ``list_slots_reference`` (a
    test oracle) is its numpy form."""
    H, W = owner.shape
    slots = np.empty((H, W), dtype=np.int64)
    ids = np.empty((H, W), dtype=np.int64)
    branches = np.empty((H, W), dtype=np.int8)
    args = (
        np.ascontiguousarray(owner, dtype=np.int64),
        np.ascontiguousarray(range_edge, dtype=np.bool_),
        np.ascontiguousarray(brightness_edge, dtype=np.bool_),
        np.ascontiguousarray(patch, dtype=np.bool_),
        np.ascontiguousarray(lut, dtype=np.int64),
        np.ascontiguousarray(list_ids, dtype=np.int64),
    )
    none = np.zeros((1, 1))  # no sums: the images are not read
    n = _list_slots_kernel(
        *args, none, none, 0.0, 0.0, branches, slots, ids, np.zeros((0, len(SUMS)))
    )
    return slots, ids, branches, _missing(slots, n)


def list_slots_and_sums(
    owner: np.ndarray,
    range_edge: np.ndarray,
    brightness_edge: np.ndarray,
    patch: np.ndarray,
    lut: np.ndarray,
    list_ids: np.ndarray,
    range_m: np.ndarray,
    intensity: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`list_slots` and, in the same pass, :func:`list_sums` of the pixels whose list
    exists (one row per slot of ``list_ids``); pixels still waiting for their list are not
    summed (sum again once :func:`fill_slots` gave them one)."""
    H, W = owner.shape
    slots = np.empty((H, W), dtype=np.int64)
    ids = np.empty((H, W), dtype=np.int64)
    branches = np.empty((H, W), dtype=np.int8)
    sums = np.zeros((list_ids.size, len(SUMS)))
    range_m = np.ascontiguousarray(range_m)  # float32 or float64 as given (compiled for each)
    intensity = np.ascontiguousarray(intensity)
    n = _list_slots_kernel(
        np.ascontiguousarray(owner, dtype=np.int64),
        np.ascontiguousarray(range_edge, dtype=np.bool_),
        np.ascontiguousarray(brightness_edge, dtype=np.bool_),
        np.ascontiguousarray(patch, dtype=np.bool_),
        np.ascontiguousarray(lut, dtype=np.int64),
        np.ascontiguousarray(list_ids, dtype=np.int64),
        range_m,
        intensity,
        range_m.dtype.type(0),
        intensity.dtype.type(0),
        branches,
        slots,
        ids,
        sums,
    )
    return slots, ids, branches, _missing(slots, n), sums


def _missing(slots: np.ndarray, n_pending: int) -> np.ndarray:
    """(M,) int64 sorted keys of the ``n_pending`` pixels of ``slots`` waiting for a list."""
    if n_pending == 0:
        return np.zeros(0, np.int64)
    return np.unique(-2 - slots[slots <= -2])


def fill_slots(slots: np.ndarray, ids: np.ndarray, lut: np.ndarray, list_ids: np.ndarray) -> None:
    """In place: the pixels :func:`list_slots` left waiting for a list (``-2 - key``) get the
    slot ``lut[key]`` and the id ``list_ids[slot]`` now that their lists exist."""
    pending = np.flatnonzero(slots.reshape(-1) <= -2)
    if pending.size:
        slot = lut[-2 - slots.reshape(-1)[pending]]
        slots.reshape(-1)[pending] = slot
        ids.reshape(-1)[pending] = np.where(slot >= 0, list_ids[np.maximum(slot, 0)], -1)


SUMS = ("n", "range", "range_step", "inten_step", "edge", "vertex", "branches", "r", "c",
        "rr", "cc", "rc")  # fmt: skip


@numba.njit(cache=True, nogil=True, inline="always")
def _accumulate(
    out: np.ndarray,
    s: int,
    i: int,
    j: int,
    range_m: np.ndarray,
    intensity: np.ndarray,
    edge: bool,
    br: int,
) -> None:
    """Add pixel (i, j) to row ``s`` of the :data:`SUMS` table ``out``."""
    H, W = range_m.shape
    r0, i0 = range_m[i, j], intensity[i, j]
    dr, di = 0.0, 0.0
    right = j + 1 if j + 1 < W else 0
    left = j - 1 if j > 0 else W - 1
    for a, b in ((i, right), (i, left)):  # range: along the row only
        d = abs(range_m[a, b] - r0)
        if d > dr and d < np.inf:  # NaN and infinite (empty) neighbours are skipped
            dr = d
    for a, b in ((i, right), (i, left), (min(i + 1, H - 1), j), (max(i - 1, 0), j)):
        d = abs(intensity[a, b] - i0)
        if d > di and d < np.inf:
            di = d
    out[s, 0] += 1.0
    out[s, 1] += r0 if abs(r0) < np.inf else 0.0
    out[s, 2] += dr
    out[s, 3] += di
    out[s, 4] += 1.0 if edge else 0.0
    out[s, 5] += 1.0 if (br == 1 or br >= 3) else 0.0
    out[s, 6] += br
    out[s, 7] += i
    out[s, 8] += j
    out[s, 9] += i * i
    out[s, 10] += j * j
    out[s, 11] += i * j


@numba.njit(cache=True, nogil=True)
def _list_sums_kernel(
    slot: np.ndarray,
    range_m: np.ndarray,
    intensity: np.ndarray,
    edge: np.ndarray,
    branches: np.ndarray,
    out: np.ndarray,
) -> None:
    H, W = slot.shape
    for i in range(H):
        for j in range(W):
            s = slot[i, j]
            if s >= 0:
                _accumulate(out, s, i, j, range_m, intensity, edge[i, j], branches[i, j])


def list_sums(
    slot: np.ndarray,
    range_m: np.ndarray,
    intensity: np.ndarray,
    edge: np.ndarray,
    branches: np.ndarray,
    n_slots: int,
) -> np.ndarray:
    """(n_slots, 12) float64 sums over the pixels of each list (``slot`` (H, W) int64 list
    index, -1 none) in :data:`SUMS` order: count, range, the largest range step to a
    neighbour along the row (between rows even flat ground steps by metres) and intensity step
    to a 4-neighbour (columns wrap, rows stop at the border, NaN or infinite neighbours
    skipped), edge and
    vertex pixels, branches, row, column and their second moments. One compiled pass;
    ``list_sums_reference`` (a test oracle) is its numpy form."""
    out = np.zeros((n_slots, len(SUMS)))
    _list_sums_kernel(
        np.ascontiguousarray(slot, dtype=np.int64),
        np.ascontiguousarray(range_m),  # float32 or float64 as given (compiled for each)
        np.ascontiguousarray(intensity),
        np.ascontiguousarray(edge, dtype=np.bool_),
        np.ascontiguousarray(branches, dtype=np.int8),
        out,
    )
    return out


def list_attributes(sums: np.ndarray, az_step_rad: float, intensity_mean: float) -> ListAttributes:
    """Attributes of the lists with pixels in ``sums`` (from :func:`list_sums`; ``ids`` are
    their slots), given the azimuth step of the image (rad) and its mean valid intensity."""
    ids = np.flatnonzero(sums[:, 0] > 0)
    t = sums[ids]
    n = t[:, 0]
    mean = t / n[:, None]
    srr = mean[:, 9] - mean[:, 7] ** 2
    scc = mean[:, 10] - mean[:, 8] ** 2
    src = mean[:, 11] - mean[:, 7] * mean[:, 8]
    return ListAttributes(
        ids=ids.astype(np.int64),
        n_pixels=n.astype(np.int64),
        range_m=mean[:, 1],
        size_m=n * mean[:, 1] * az_step_rad,
        range_jump_m=mean[:, 2],
        contrast=mean[:, 3] / max(intensity_mean, 1e-12),
        edge_share=mean[:, 4],
        vertex_share=mean[:, 5],
        branches=mean[:, 6],
        orientation_rad=np.mod(0.5 * np.arctan2(2.0 * src, scc - srr), np.pi),
    )

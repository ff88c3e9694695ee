"""Grouping on the egosphere image: level-4 object hypotheses and level-2 range edges.

Reference 001, 4.5.1 (grouping: "gestalt" hypotheses of proximity, similarity, continuity),
4.5.6 (level 2: edges, vertices; level 4: objects grouped by contiguity and similar range,
"boundaries that separate surfaces with different range ... distinguish between different
objects").

Objects: non-ground returns are joined to their image neighbours (right, below, the
next-but-one along the row so a dropped return does not split a surface, and the next row
with a return when up to ``row_gap`` rows between hold none, as an elevation-binned image of a
sparse beam pattern has) when the two points are closer than a range-scaled distance (the
grazing-angle rule: proximity and contiguity) or than the ``join_m`` floor, unless the range
steps between them (:func:`_range_step`: an occluder's edge, a person or a car before a
building front, is a step; a surface, even one seen at a grazing angle, continues). The
connected components of that graph are the object hypotheses; small pieces within ``near_m``
of each other in 3D are one when far enough for the beams to lie apart (proximity: a
bicycle seen through). Components with fewer than
``min_pixels`` returns are left ungrouped (speckle). Azimuth wraps around.

Continuity (:func:`merge_collinear`): a long straight segment (a wall, a fence, a building
face) that an occluder or a grazing angle cut into pieces is joined again when the pieces lie
on its axis with a short gap between them and are thin across it (a person or a car beside
the wall is not a piece of it).

Edges (level 2): pixels whose range jumps by more than ``edge_jump_m`` (plus a fraction of the
range) to a neighbour, each labelled by the object or the ground it lies on.

:func:`label_objects` tests the links and joins the pixels in one compiled pass (numba, a
union-find); :func:`label_objects_reference` is the numpy and scipy form it is tested against
(the same labels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from core.errors import EngineError
from sp.nan_ops import maximum as _maximum
from sp.nan_ops import minimum as _minimum


class SegmentError(EngineError, ValueError):
    """An image or configuration the grouping cannot use; names the value."""


@dataclass(frozen=True)
class SegmentConfig:
    """Grouping thresholds.

    join_m:          two neighbouring returns closer than this (metres) belong together ...
    join_per_rad:    ... or closer than this many times the range times their angular spacing
                     (the sensor's own point spacing grows with range), along a row (large
                     enough to join a wall seen at a grazing angle) ...
    join_per_rad_row: ... and across rows.
    min_pixels:      smallest object hypothesis (returns).
    line_*:          continuity: a segment at least ``line_min_length_m`` long and
                     ``line_min_aspect`` times longer than wide is a line; another segment whose
                     centre lies within ``line_offset_m`` of that line, whose extent along it
                     leaves a gap of at most ``line_gap_m`` (both plus ``line_per_m`` per metre
                     of range), which is at most ``line_thick_m`` wide (across its own long
                     axis), and which is short (under 2 m) or turned by at most
                     ``line_max_turn_deg`` from it, continues it.
    step_m, step_frac: no join across a range step larger than ``step_m + step_frac * range``
                     (metres) that continues neither side (0 turns the test off).
    row_gap:         a return is joined to the next one down its column across at most this
                     many rows without any return.
    near_pixels, near_m, near_min_range_m: beyond ``near_min_range_m`` (metres), pieces of
                     fewer returns than ``near_pixels`` whose points come closer than ``near_m``
                     (metres, 3D) are one piece.
    edge_jump_m, edge_jump_frac: a range edge is a jump of ``edge_jump_m + frac * range``.
    hidden_span_m, hidden_front_m: behind an occluder (:func:`merge_behind_occluders`): two
                     segments whose ends on a row face each other across a run of returns
                     in front of both, at ranges that continue each other (the step
                     threshold), are one when the run hides at most ``hidden_span_m``
                     (metres across the line of sight; 0 turns the rule off) and its
                     returns lie at least ``hidden_front_m`` in front of both ends.
    graze_*:         a face seen at a grazing angle: thin pieces (at most ``graze_thick_m``
                     across) at most ``graze_cols`` columns apart in azimuth, whose centres
                     lie along the line of sight (within ``graze_max_deg`` of it) at most
                     ``graze_gap_m + graze_gap_per_m * range`` apart, and whose tops differ by
                     at most ``graze_dz_m``, are one piece, as long as all the pieces' centres
                     stay within ``graze_thick_m`` of one line.
    """

    join_m: float = 0.6
    join_per_rad: float = 6.0
    join_per_rad_row: float = 2.5
    min_pixels: int = 4
    edge_jump_m: float = 0.5
    edge_jump_frac: float = 0.05
    line_min_length_m: float = 3.0
    line_min_aspect: float = 3.0
    line_offset_m: float = 0.5
    line_gap_m: float = 1.5
    line_per_m: float = 0.03
    line_max_turn_deg: float = 15.0
    line_thick_m: float = 0.4
    step_m: float = 0.2
    step_frac: float = 0.01
    hidden_span_m: float = 2.0
    hidden_front_m: float = 2.0
    graze_thick_m: float = 0.15
    graze_cols: float = 3.0
    graze_max_deg: float = 20.0
    graze_gap_m: float = 0.5
    graze_gap_per_m: float = 0.1
    graze_dz_m: float = 1.0
    row_gap: int = 2
    near_pixels: int = 10
    near_m: float = 0.4
    near_min_range_m: float = 15.0

    def __post_init__(self) -> None:
        if self.join_m <= 0 or self.join_per_rad < 0 or self.min_pixels < 1:
            raise SegmentError(
                f"join_m {self.join_m}, join_per_rad {self.join_per_rad}, "
                f"min_pixels {self.min_pixels}: need > 0, >= 0, >= 1"
            )
        if self.step_m < 0 or self.row_gap < 0 or self.near_m < 0:
            raise SegmentError(
                f"step_m {self.step_m}, row_gap {self.row_gap}, near_m {self.near_m}: "
                "need >= 0 (0 turns the rule off)"
            )


def label_objects(
    xyz: np.ndarray,
    range_m: np.ndarray,
    mask: np.ndarray,
    row_step_rad: float,
    col_step_rad: float,
    config: SegmentConfig | None = None,
) -> np.ndarray:
    """Object hypotheses: (H, W) int64 segment labels 0..K-1, -1 where not grouped.

    xyz: (H, W, 3) float points (any frame, metres); range_m: (H, W) range from the sensor
    (non-finite or <= 0 where there is no return); mask: (H, W) bool pixels to group (valid,
    non-ground); row_step_rad, col_step_rad: the angular spacing of rows and columns.

    The links and the union-find over them are one compiled pass (:func:`_components_kernel`),
    with the same arithmetic in the same dtypes as :func:`label_objects_reference` and the
    components numbered as scipy's ``connected_components`` numbers them (by first
    appearance in flat pixel order), so the labels are the reference's. Inputs the kernel is
    not built for (xyz or range_m not float32 / float64, a non-bool mask, xyz not (H, W, 3))
    take the reference path.
    """
    cfg = config or SegmentConfig()
    H, W = mask.shape
    if xyz.shape[:2] != (H, W) or range_m.shape != (H, W):
        raise SegmentError(f"xyz {xyz.shape} / range {range_m.shape} do not match mask {(H, W)}")
    floats = (np.dtype(np.float32), np.dtype(np.float64))
    if (
        xyz.ndim != 3
        or xyz.shape[2] != 3
        or xyz.dtype not in floats
        or range_m.dtype not in floats
        or mask.dtype != np.bool_
    ):
        return label_objects_reference(xyz, range_m, mask, row_step_rad, col_step_rad, cfg)
    pts = np.ascontiguousarray(xyz)
    contig_range_m = np.ascontiguousarray(range_m)
    m = np.ascontiguousarray(mask)
    R = contig_range_m.dtype
    # the step scalars exactly as the reference forms them (Python or numpy floats), each cast
    # to the dtype numpy computes its expression in, so the kernel's float32 / float64 scalar
    # arithmetic is the reference's array arithmetic (a float32 range times a Python float is
    # a float32 product; the range step's own tests are float64)
    s01 = col_step_rad * cfg.join_per_rad
    s02 = 2 * col_step_rad * cfg.join_per_rad
    downs = [k * row_step_rad * cfg.join_per_rad_row for k in range(1, cfg.row_gap + 2)]
    P01, P02, Pd = np.result_type(R, s01), np.result_type(R, s02), np.result_type(R, downs[0])
    S1 = np.result_type(cfg.step_frac, R)
    idx, comp, counts = _components_kernel(
        pts,
        contig_range_m,
        m,
        P01.type(s01),
        P02.type(s02),
        np.array(downs, dtype=Pd),
        _cast(cfg.join_m, P01),
        _cast(cfg.join_m, P02),
        _cast(cfg.join_m, Pd),
        bool(cfg.step_m > 0),
        S1.type(cfg.step_frac),
        _cast(cfg.step_m, S1),
        float(cfg.step_frac),
        float(cfg.step_m),
        int(cfg.row_gap),
    )
    group, n_groups = np.arange(counts.size, dtype=np.int64), counts.size
    if cfg.near_pixels > 0 and cfg.near_m > 0 and counts.size > 1:
        group, n_groups = _near_groups(
            comp, counts, idx, pts.reshape(-1, 3), contig_range_m.reshape(-1), cfg
        )
    return _keep_kernel(idx, comp, group, n_groups, cfg.min_pixels, H * W).reshape(H, W)


def _cast(value: float, dtype: np.dtype) -> np.generic:
    """``value`` in the dtype numpy computes ``value op x`` in for an array x of ``dtype``."""
    return np.result_type(value, dtype).type(value)


def _near_groups(
    comp: np.ndarray,
    counts: np.ndarray,
    idx: np.ndarray,
    points: np.ndarray,
    range_m: np.ndarray,
    cfg: SegmentConfig,
) -> tuple[np.ndarray, int]:
    """:func:`_join_near_pieces` for :func:`label_objects`: (K,) int64 group of each of the K
    components and the number of groups, numbered by each group's smallest component (as
    ``connected_components`` numbers them).

    comp: (n,) int64 component of each grouped pixel; counts: (K,) their sizes; idx: (n,)
    int64 the pixels' flat indices (flat order); points: (H * W, 3) float points (m);
    range_m: (H * W,) ranges (m). The small far pixels are chosen by the reference's own
    numpy expressions and handed to the same ``cKDTree`` in the same order, so the pairs are
    the reference's pairs; only the graph over the components is a union-find, not scipy's.
    """
    from scipy.spatial import cKDTree

    K = counts.size
    small = np.flatnonzero((counts[comp] < cfg.near_pixels) & (range_m[idx] > cfg.near_min_range_m))
    if small.size >= 2:
        pairs = cKDTree(points[idx[small]]).query_pairs(cfg.near_m, output_type="ndarray")
        if pairs.size:
            return _merge_kernel(comp[small[pairs[:, 0]]], comp[small[pairs[:, 1]]], K)
    return np.arange(K, dtype=np.int64), K


@numba.njit(cache=True, nogil=True)
def _find(parent, x):  # pragma: no cover
    """Root of x, halving the path on the way (parent: (n,) int32 / int64, modified)."""
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


@numba.njit(cache=True, nogil=True)
def _union(parent, ra, b):  # pragma: no cover
    """Join the set of root ``ra`` and that of b; returns the joined set's root, the smaller
    of the two (so the first pixel of a component in flat order is its root, which numbers
    the components by first appearance)."""
    rb = _find(parent, b)
    if ra < rb:
        parent[rb] = ra
        return ra
    parent[ra] = rb
    return rb


@numba.njit(cache=True, nogil=True)
def _wrap(j, W):  # pragma: no cover
    """j mod W for a column index at most a few columns outside 0..W-1."""
    while j >= W:
        j -= W
    while j < 0:
        j += W
    return j


@numba.njit(cache=True, nogil=True)
def _r64(x):  # pragma: no cover
    """:func:`_ranges` of one range: float64, NaN where there is no return."""
    v = np.float64(x)
    return v if (v > 0.0 and v < np.inf) else np.nan


@numba.njit(cache=True, nogil=True)
def _step_cut(range_m, ia, ja, ib, jb, di, dj, sf64, sm64):  # pragma: no cover
    """:func:`_range_step` of the one link (ia, ja) -> (ib, jb) = (ia + di, (ja + dj) mod W):
    the same float64 differences, NaN where a side has no return or lies off the image."""
    H, W = range_m.shape
    r_a = _r64(range_m[ia, ja])
    r_b = _r64(range_m[ib, jb])
    ip = ia - di
    iq = ib + di
    r_p = _r64(range_m[ip, _wrap(ja - dj, W)]) if ip >= 0 else np.nan
    r_q = _r64(range_m[iq, _wrap(jb + dj, W)]) if iq < H else np.nan
    s = r_b - r_a
    before = r_a - r_p
    after = r_q - r_b
    thr = sm64 + sf64 * _minimum(r_a, r_b)
    disc = _minimum(abs(s - before) - abs(before), abs(s - after) - abs(after))
    cut = abs(s) > thr and disc > thr
    if di > 0:
        cut = cut and s < 0
    return cut


@numba.njit(cache=True, nogil=True, inline="always")
def _skip_ok(r_a, r_mid, r_b, sf, sm):  # pragma: no cover
    """:func:`_skips_ok` of one link: the pixel between holds no return, or one in front of
    both ends by more than the step threshold ``sm + sf * r`` (r the nearer end's range)."""
    if not (r_mid > 0 and r_mid < np.inf):
        return True
    r = _minimum(r_a, r_b)
    return r_mid < r - (sm + sf * r)


# inlined into the kernel: a call per link, with two arrays to pass, would cost more than the test
@numba.njit(cache=True, nogil=True, inline="always")
def _joined(
    xyz, range_m, ia, ja, ib, jb, di, dj, step, join_m, step_on, sf, sm, sf64, sm64
):  # pragma: no cover
    """The reference's link test for one pixel pair: closer than ``max(join_m, r * step)``
    (r the nearer range) and not across a range step. The distance is formed in xyz's dtype
    and summed x, y, z in that order (as ``np.linalg.norm`` sums), the limit in the dtypes of
    ``step`` / ``join_m``; NaN compares false as in numpy."""
    dx = xyz[ia, ja, 0] - xyz[ib, jb, 0]
    dy = xyz[ia, ja, 1] - xyz[ib, jb, 1]
    dz = xyz[ia, ja, 2] - xyz[ib, jb, 2]
    d = np.sqrt(dx * dx + dy * dy + dz * dz)
    ra = range_m[ia, ja]
    rb = range_m[ib, jb]
    r = _minimum(ra, rb)
    if not d <= _maximum(join_m, r * step):
        return False
    # only a link whose ranges differ by more than the step threshold can cross a step
    if not step_on or not abs(ra - rb) > sm + sf * r:
        return True
    return not _step_cut(range_m, ia, ja, ib, jb, di, dj, sf64, sm64)


@numba.njit(cache=True, nogil=True)
def _components_kernel(
    xyz, range_m, mask, s01, s02, downs, jm01, jm02, jmd, step_on, sf, sm, sf64, sm64, row_gap
):  # pragma: no cover
    """The links of :func:`label_objects_reference` and their connected components.

    xyz (H, W, 3), range_m (H, W) float32 or float64; mask (H, W) bool; s01, s02: the row-link
    steps (next, next-but-one pixel); downs (row_gap + 1,): the column-link steps k = 1..
    rows down; jm*: join_m for each; step_on, sf, sm: the range-step prefilter (``step_m > 0``,
    step_frac, step_m in the range's dtype); sf64, sm64: the same in float64 for
    :func:`_step_cut`. Returns idx (n,) int64 the flat indices of the n mask pixels in flat
    order, comp (n,) int64 the component of each (0..K-1 by first appearance in flat order,
    as ``connected_components`` numbers the reference's compacted graph) and counts (K,)
    int64 their sizes.
    """
    H, W = mask.shape
    # the union-find runs on the compacted mask pixels (pos: flat index -> compact index),
    # a small array that stays in cache, not on every pixel of the image
    pos = np.empty(H * W, dtype=np.int32)
    idx = np.empty(H * W, dtype=np.int64)
    n = 0
    for i in range(H):
        for j in range(W):
            if mask[i, j]:
                pos[i * W + j] = n
                idx[n] = i * W + j
                n += 1
    parent = np.arange(n, dtype=np.int32)
    for i in range(H):
        for j in range(W):
            if not mask[i, j]:
                continue
            # the root of this pixel's set, kept through its unions (one find per link)
            root = _find(parent, pos[i * W + j])
            # azimuth wraps (a subtraction, not an integer division per pixel)
            j1 = _wrap(j + 1, W)
            if mask[i, j1] and _joined(
                xyz, range_m, i, j, i, j1, 0, 1, s01, jm01, step_on, sf, sm, sf64, sm64
            ):
                root = _union(parent, root, pos[i * W + j1])
            j2 = _wrap(j + 2, W)
            if (
                mask[i, j2]
                and _skip_ok(range_m[i, j], range_m[i, j1], range_m[i, j2], sf, sm)
                and _joined(xyz, range_m, i, j, i, j2, 0, 2, s02, jm02, step_on, sf, sm, sf64, sm64)
            ):
                root = _union(parent, root, pos[i * W + j2])
            # down the column: the next row, then the rows after it while those between
            # hold no return (the reference's ``empty``: no finite range > 0)
            for k in range(1, row_gap + 2):
                ib = i + k
                if ib >= H:
                    break
                if k >= 2:
                    r_mid = range_m[ib - 1, j]
                    if r_mid > 0 and r_mid < np.inf:
                        break
                if mask[ib, j] and _joined(
                    xyz, range_m, i, j, ib, j, k, 0, downs[k - 1], jmd, step_on, sf, sm, sf64, sm64
                ):
                    root = _union(parent, root, pos[ib * W + j])
    comp = np.empty(n, dtype=np.int64)
    counts = np.zeros(n, dtype=np.int64)
    K = 0
    for p in range(n):
        r = _find(parent, p)
        # a component's root is its first pixel in flat order, numbered when it is met
        if r == p:
            comp[p] = K
            K += 1
        else:
            comp[p] = comp[r]
        counts[comp[p]] += 1
    return idx[:n], comp, counts[:K]


@numba.njit(cache=True, nogil=True)
def _merge_kernel(ca, cb, K):  # pragma: no cover
    """Components ca[k] and cb[k] ((m,) int64) are one: (K,) int64 group of each component,
    numbered by its smallest component (as ``connected_components`` numbers a graph's
    components), and the number of groups."""
    parent = np.arange(K)
    for k in range(ca.size):
        _union(parent, _find(parent, ca[k]), cb[k])
    group = np.empty(K, dtype=np.int64)
    n = 0
    for c in range(K):
        r = _find(parent, c)
        if r == c:
            group[c] = n
            n += 1
        else:
            group[c] = group[r]
    return group, n


@numba.njit(cache=True, nogil=True)
def _keep_kernel(idx, comp, group, n_groups, min_pixels, size):  # pragma: no cover
    """(size,) int64 labels: the groups of at least ``min_pixels`` pixels numbered 0..K-1 in
    group order, -1 elsewhere. idx (n,) int64 flat index and comp (n,) int64 component of
    each grouped pixel; group (K,) int64 the group of each component."""
    counts = np.zeros(n_groups, dtype=np.int64)
    for p in range(comp.size):
        counts[group[comp[p]]] += 1
    new_id = np.full(n_groups, -1, dtype=np.int64)
    k = 0
    for g in range(n_groups):
        if counts[g] >= min_pixels:
            new_id[g] = k
            k += 1
    labels = np.full(size, -1, dtype=np.int64)
    for p in range(comp.size):
        labels[idx[p]] = new_id[group[comp[p]]]
    return labels


def label_objects_reference(
    xyz: np.ndarray,
    range_m: np.ndarray,
    mask: np.ndarray,
    row_step_rad: float,
    col_step_rad: float,
    config: SegmentConfig | None = None,
) -> np.ndarray:
    """:func:`label_objects` in numpy and scipy (the reference the compiled kernel is tested
    against; same arguments, same labels): the links of each kind in arrays, the components
    by ``scipy.sparse.csgraph.connected_components``.
    """
    cfg = config or SegmentConfig()
    H, W = mask.shape
    if xyz.shape[:2] != (H, W) or range_m.shape != (H, W):
        raise SegmentError(f"xyz {xyz.shape} / range {range_m.shape} do not match mask {(H, W)}")
    flat = xyz.reshape(-1, 3)
    range_flat_m = range_m.reshape(-1)
    empty = ~(np.isfinite(range_m) & (range_m > 0)) if cfg.row_gap > 0 else None
    steps = [
        (0, 1, col_step_rad * cfg.join_per_rad),
        (0, 2, 2 * col_step_rad * cfg.join_per_rad),
        (1, 0, row_step_rad * cfg.join_per_rad_row),
    ]
    steps += [(k, 0, k * row_step_rad * cfg.join_per_rad_row) for k in range(2, cfg.row_gap + 2)]
    src, dst = [], []
    for di, dj, step in steps:
        if di >= H:
            continue
        a, b = _links(mask, di, dj, empty)
        if dj == 2:
            keep = _skips_ok(range_flat_m, a, b, W, cfg)
            a, b = a[keep], b[keep]
        d = np.linalg.norm(flat[a] - flat[b], axis=1)
        r = np.minimum(range_flat_m[a], range_flat_m[b])
        near = d <= np.maximum(cfg.join_m, r * step)
        if cfg.step_m > 0:
            # no join across a step in range (an occluder's edge); only a link whose range
            # differs by more than the step threshold can be one
            with np.errstate(invalid="ignore"):
                big = near & (
                    np.abs(range_flat_m[a] - range_flat_m[b]) > cfg.step_m + cfg.step_frac * r
                )
            f = np.flatnonzero(big)
            near[f] = ~_range_step(range_flat_m, a[f], b[f], di, dj, (H, W), cfg)
        src.append(a[near])
        dst.append(b[near])
    idx = np.flatnonzero(mask.reshape(-1))
    labels = np.full(H * W, -1, dtype=np.int64)
    if idx.size == 0:
        return labels.reshape(H, W)
    # compact the graph to the grouped pixels only
    pos = np.full(H * W, -1, dtype=np.int64)
    pos[idx] = np.arange(idx.size)
    s = pos[np.concatenate(src)] if src else np.zeros(0, np.int64)
    t = pos[np.concatenate(dst)] if dst else np.zeros(0, np.int64)
    g = coo_matrix((np.ones(s.size, dtype=np.int8), (s, t)), shape=(idx.size, idx.size))
    _, comp = connected_components(g, directed=False)
    if cfg.near_pixels > 0 and cfg.near_m > 0:
        comp = _join_near_pieces(comp, flat[idx], range_flat_m[idx], cfg)
    counts = np.bincount(comp)
    keep = counts >= cfg.min_pixels
    new_id = np.full(counts.size, -1, dtype=np.int64)
    new_id[keep] = np.arange(int(keep.sum()))
    labels[idx] = new_id[comp]
    return labels.reshape(H, W)


def _join_near_pieces(
    comp: np.ndarray, points: np.ndarray, range_m: np.ndarray, cfg: SegmentConfig
) -> np.ndarray:
    """Proximity in 3D (reference 001, 4.5.1: "subentities are close together"): beyond
    ``near_min_range_m``, where the beams lie too far apart for image contiguity to hold a thin
    object together (a bicycle seen through), pieces of fewer than ``near_pixels`` returns
    whose points come closer than ``near_m`` to each other are one piece.
    comp: (n,) component of each grouped pixel; points: (n, 3) their points (m); range_m:
    (n,) their ranges (m). Returns the new (n,) components, numbered 0..K-1."""
    from scipy.spatial import cKDTree

    counts = np.bincount(comp)
    small = np.flatnonzero((counts[comp] < cfg.near_pixels) & (range_m > cfg.near_min_range_m))
    if small.size < 2:
        return comp
    pairs = cKDTree(points[small]).query_pairs(cfg.near_m, output_type="ndarray")
    if pairs.size == 0:
        return comp
    a, b = comp[small[pairs[:, 0]]], comp[small[pairs[:, 1]]]
    K = counts.size
    g = coo_matrix((np.ones(a.size, dtype=np.int8), (a, b)), shape=(K, K))
    _, new = connected_components(g, directed=False)
    return new[comp]


def _links(
    mask: np.ndarray, di: int, dj: int, empty: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (a, b) of the pixel pairs (i, j) - (i + di, (j + dj) mod W) both in
    ``mask`` (azimuth wraps); for di > 1 only across rows that hold no return at column j
    (``empty`` (H, W) bool), so a sparse beam pattern does not split a surface."""
    H, W = mask.shape
    lower = mask[di:] if dj == 0 else np.roll(mask, -dj, axis=1)[di:]
    ok = mask[: H - di] & lower
    for k in range(1, di):
        ok &= empty[k : H - di + k]
    a = np.flatnonzero(ok)
    b = a + di * W if dj == 0 else (a // W + di) * W + (a % W + dj) % W
    return a, b


def _skips_ok(
    range_flat_m: np.ndarray, a: np.ndarray, b: np.ndarray, W: int, cfg: SegmentConfig
) -> np.ndarray:
    """(n,) bool: the next-but-one links a -> b (flat indices, b two columns on) may skip the
    pixel between them. They may when it holds no return (a dropout) or a return in front of
    both ends by more than the step threshold (an occluder, such as a post before a wall).
    A return between the two in range, or behind both (the background seen through a gap
    between two cars parked nose to tail), leaves the direct links to decide: skipping it
    would join across the very boundary it shows."""
    mid = (a // W) * W + (a % W + 1) % W
    r_mid = range_flat_m[mid]
    r = np.minimum(range_flat_m[a], range_flat_m[b])
    with np.errstate(invalid="ignore"):
        hit = (r_mid > 0) & (r_mid < np.inf)
        front = r_mid < r - (cfg.step_m + cfg.step_frac * r)
    return ~hit | front


def _neighbour(
    p: np.ndarray, di: int, dj: int, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Flat index of pixel p moved by (di, dj) (azimuth wraps) and whether it is inside."""
    H, W = shape
    i, j = np.divmod(p, W)
    i2 = i + di
    inside = (i2 >= 0) & (i2 < H)
    return np.clip(i2, 0, H - 1) * W + (j + dj) % W, inside


def _range_step(
    range_m: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    di: int,
    dj: int,
    shape: tuple[int, int],
    cfg: SegmentConfig,
) -> np.ndarray:
    """(n,) bool: the links a -> b (flat pixel indices, b = a moved by (di, dj)) cross a step
    in range. range_m: (H * W,) range, non-finite or <= 0 where there is no return.

    Continuity and discontinuity of range (reference 001, 4.5.1 grouping by continuity; 4.5.6
    level 4: "boundaries that separate surfaces with different range ... distinguish between
    different objects"): along one surface, even one seen at a grazing angle, the range
    changes smoothly, so the range difference ``s = r_b - r_a`` of a link continues that of
    the link before it (``r_a - r_before``) or after it (``r_after - r_b``); a surface curving
    away (a limb) lets the differences grow, so the slack grows with them. An occluding
    boundary (a person before a wall) is a step that continues neither side:
    ``|s| > thr`` and ``|s - s_side| - |s_side| > thr`` on both sides, with
    ``thr = step_m + step_frac * range``. Both sides must hold returns: at a silhouette (a box's
    one row of roof against the sky) a step cannot be told from a crease, and the link stays.
    Down the image (di > 0) only a step whose upper pixel is the farther one cuts: the top edge
    of an occluder; a nearer upper pixel is an overhang (a tree's crown over its trunk, eaves)
    and stays joined.
    """
    p, p_in = _neighbour(a, -di, -dj, shape)
    q, q_in = _neighbour(b, di, dj, shape)
    r_a, r_b = _ranges(range_m, a), _ranges(range_m, b)
    r_p = np.where(p_in, _ranges(range_m, p), np.nan)
    r_q = np.where(q_in, _ranges(range_m, q), np.nan)
    s = r_b - r_a
    before, after = r_a - r_p, r_q - r_b
    thr = cfg.step_m + cfg.step_frac * np.minimum(r_a, r_b)
    disc = np.minimum(np.abs(s - before) - np.abs(before), np.abs(s - after) - np.abs(after))
    with np.errstate(invalid="ignore"):
        cut = (np.abs(s) > thr) & (disc > thr)
    if di > 0:
        cut &= s < 0
    return cut


def _ranges(range_m: np.ndarray, p: np.ndarray) -> np.ndarray:
    """range_m[p] as float64, NaN where there is no return."""
    r = range_m[p].astype(np.float64)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(r) & (r > 0), r, np.nan)


def split_by_predictions(
    labels: np.ndarray,
    points_world: np.ndarray,
    centres_xy: np.ndarray,
    seg_center_xy: np.ndarray,
    seg_radius_m: np.ndarray,
    near_m: float,
    min_apart_m: float,
    min_pixels: int,
) -> np.ndarray:
    """Cut a segment that holds the predicted places of two or more tracked people (walkers
    side by side, whom proximity joins: ``join_m`` bridges the half metre between them):
    each of its returns goes to the nearest prediction (in the horizontal plane). This is
    grouping windowed by the world model's predictions (reference 001, 4.5.1: "predicted
    entities ... to set windows"); a segment with one prediction, or whose predictions are
    closer than ``min_apart_m``, stays whole, and so does one a part of which would be
    smaller than ``min_pixels`` returns.

    labels (H, W) int64 (-1 none, 0..K-1); points_world (H, W, 3) m; centres_xy (C, 2) world
    xy of the predicted people, m; seg_center_xy (K, 2) and seg_radius_m (K,) each segment's
    footprint centre and half diagonal (only segments reaching two predictions are looked
    at); a prediction counts for a segment when one of its returns lies within ``near_m`` of
    it. Returns new labels, the cut-off parts numbered from K on, or ``labels`` itself when
    nothing was cut.
    """
    if len(centres_xy) < 2 or len(seg_center_xy) == 0:
        return labels
    reach = np.linalg.norm(seg_center_xy[:, None, :] - centres_xy[None, :, :], axis=2)
    reach = reach <= seg_radius_m[:, None] + near_m  # (K, C)
    out, next_label = labels, int(labels.max()) + 1
    for k in np.flatnonzero(reach.sum(axis=1) >= 2):
        rows, cols = np.nonzero(labels == k)
        xy = points_world[rows, cols, :2]
        cs = np.flatnonzero(reach[k])
        d = np.linalg.norm(xy[:, None, :] - centres_xy[cs][None, :, :], axis=2)  # (n, c)
        cs_in = d.min(axis=0) <= near_m
        if cs_in.sum() < 2:
            continue
        cs, d = cs[cs_in], d[:, cs_in]
        c_xy = centres_xy[cs]
        gaps = np.linalg.norm(c_xy[:, None] - c_xy[None], axis=2)[np.triu_indices(len(cs), 1)]
        if gaps.min() < min_apart_m:
            continue
        part = np.argmin(d, axis=1)
        if np.bincount(part, minlength=len(cs)).min() < min_pixels:
            continue
        if out is labels:
            out = labels.copy()
        for j in range(1, len(cs)):
            out[rows[part == j], cols[part == j]] = next_label
            next_label += 1
    return out


def split_at_gap(
    labels: np.ndarray,
    points_world: np.ndarray,
    yaw_rad: np.ndarray,
    length_m: np.ndarray,
    width_m: np.ndarray,
    height_m: np.ndarray,
    gap_m: float,
    max_length_m: float,
    max_width_m: float,
    min_height_m: float,
    min_pixels: int,
) -> np.ndarray:
    """Cut a narrow upright segment in two where its returns, projected on its long axis,
    leave a gap of at least ``gap_m``: two people side by side, whom proximity joined before
    either was tracked (a gap of a third of a metre between their shoulders; one person's
    returns lie a few centimetres apart). This is the grouping hypothesis of proximity
    (reference 001, 4.5.1) tested on the segment's own returns: a body is continuous, a
    pair is not. Only segments at most ``max_length_m`` long, ``max_width_m`` wide and
    ``min_height_m`` tall are looked at (a car or a wall is longer or wider), and a cut
    leaving a side of fewer than ``min_pixels`` returns is not made.

    labels (H, W) int64 (-1 none, 0..K-1); points_world (H, W, 3) m; yaw_rad, length_m,
    width_m, height_m (K,) each segment's footprint axis and extents. Returns new labels, the
    cut-off parts numbered from K on, or ``labels`` itself when nothing was cut.
    """
    look = np.flatnonzero(
        (length_m <= max_length_m) & (width_m <= max_width_m) & (height_m >= min_height_m)
        & (length_m >= gap_m + 0.2)
    )  # fmt: skip
    out, next_label = labels, int(labels.max(initial=-1)) + 1
    if look.size == 0:
        return out
    # the looked-at segments' pixels (flat indices), grouped by segment in one stable sort,
    # each group in row-major order
    flat = labels.reshape(-1)
    pix = np.flatnonzero(np.isin(flat, look))
    lab = flat[pix]
    by_label = np.argsort(lab, kind="stable")
    pix, lab = pix[by_label], lab[by_label]
    start, end = np.searchsorted(lab, look, "left"), np.searchsorted(lab, look, "right")
    xy = points_world.reshape(-1, 3)[:, :2]
    for k, s, e in zip(look.tolist(), start.tolist(), end.tolist(), strict=True):
        if e - s < 2 * min_pixels:
            continue
        mine = pix[s:e]
        axis = np.array([math.cos(yaw_rad[k]), math.sin(yaw_rad[k])])
        u = xy[mine] @ axis
        order = np.argsort(u)
        gaps = np.diff(u[order])
        j = int(np.argmax(gaps))
        if gaps[j] < gap_m or min(j + 1, u.size - j - 1) < min_pixels:
            continue
        if out is labels:
            out = labels.copy()
        out.reshape(-1)[mine[order[j + 1 :]]] = next_label
        next_label += 1
    return out


def merge_behind_occluders(
    labels: np.ndarray,
    range_m: np.ndarray,
    col_step_rad: float,
    config: SegmentConfig | None = None,
) -> np.ndarray:
    """Continuity behind an occluder: (K,) int64 new label of each of the K segments of
    ``labels`` (0..K'-1, in order of the smallest old label), the pieces of one surface that
    something in front cut apart sharing a label.

    A person or a post in front of a parked car splits the car's returns in the image into a
    piece each side of it; contiguity cannot join them, and each piece becomes an object of
    its own. Along a row, two segments whose facing ends are separated only by returns in
    front of both (by the range-step threshold ``step_m + step_frac * r``; a single column
    without a return between two of them is a dropout), at ranges that continue each
    other (their difference within the same threshold), are one surface seen past the
    occluder (reference 001, 4.5.1: grouping by continuity; 4.5.6: range boundaries separate
    objects, and here the only boundary is the occluder's own). Where the run shows anything
    behind the occluder, something farther than the pieces (the ground, or the far side of
    a gap between two parked cars) or nothing at all (the sky through that gap), they stay
    apart. The run may hide at most ``hidden_span_m`` across the line of sight, and its
    returns must lie at least ``hidden_front_m`` in front of both pieces: among people walking
    together, one in front of two others is less than that nearer, and the two are not one
    surface.

    labels (H, W) int64 (-1 none, 0..K-1); range_m (H, W) m (non-finite or <= 0: no return);
    col_step_rad the egosphere's column step (rad).
    """
    cfg = config or SegmentConfig()
    K = int(labels.max(initial=-1)) + 1
    if K < 2 or cfg.hidden_span_m <= 0:
        return np.arange(K, dtype=np.int64)
    r = np.where(np.isfinite(range_m) & (range_m > 0), range_m, np.nan).astype(np.float64)
    a, b = _occluded_pairs(
        np.ascontiguousarray(labels, dtype=np.int64), np.ascontiguousarray(r),
        float(col_step_rad), float(cfg.step_m), float(cfg.step_frac), float(cfg.hidden_span_m),
        float(cfg.hidden_front_m),
    )  # fmt: skip
    return _merge_kernel(a, b, K)[0]


@numba.njit(cache=True, nogil=True)
def _occluded_pairs(labels, r, col_step, step_m, step_frac, span_m, front_m):  # pragma: no cover
    """(a, b) int64 label pairs of :func:`merge_behind_occluders`: from each labelled pixel
    whose right neighbour is in front of it, the run to the right is followed while it stays
    so; the first pixel behind the run closes it."""
    H, W = labels.shape
    out_a = []
    out_b = []
    for i in range(H):
        for j in range(W):
            a = labels[i, j]
            ra = r[i, j]
            if a < 0 or not (ra > 0.0):
                continue
            max_cols = min(int(span_m / (col_step * ra)) + 1, W // 4)
            k = _wrap(j + 1, W)
            hidden = 0
            front = False  # the last pixel of the run holds a return in front
            far_front = 0.0  # the farthest return in the run
            while hidden <= max_cols:
                rk = r[i, k]
                if rk > 0.0 and rk < ra - (step_m + step_frac * rk):
                    front = True
                    far_front = max(far_front, rk)
                elif not (rk > 0.0) and front:
                    front = False  # a dropout within the occluder, not a gap beside it
                else:
                    break
                hidden += 1
                k = _wrap(k + 1, W)
            if hidden > max_cols or not front:
                continue
            b = labels[i, k]
            rb = r[i, k]
            if b < 0 or b == a:
                continue
            near = min(ra, rb)
            thr = step_m + step_frac * near
            if abs(ra - rb) > thr or far_front > near - front_m:
                continue
            if hidden * col_step * near > span_m:
                continue
            out_a.append(a)
            out_b.append(b)
    na = np.empty(len(out_a), dtype=np.int64)
    nb = np.empty(len(out_b), dtype=np.int64)
    for n in range(len(out_a)):
        na[n] = out_a[n]
        nb[n] = out_b[n]
    return na, nb


def merge_collinear(
    center_xy: np.ndarray,
    yaw_rad: np.ndarray,
    length_m: np.ndarray,
    width_m: np.ndarray,
    range_m: np.ndarray,
    config: SegmentConfig | None = None,
) -> np.ndarray:
    """Continuity of lines: (K,) int64 new label of each of K segments (0..K'-1, in order of
    first appearance), pieces of one line sharing a label.

    center_xy (K, 2) m footprint centres, yaw_rad (K,) long-axis headings, length_m / width_m
    (K,) extents along and across it, range_m (K,) nearest range from the sensor.
    """
    cfg = config or SegmentConfig()
    K = center_xy.shape[0]
    parent = np.arange(K)
    line = (length_m >= cfg.line_min_length_m) & (
        length_m >= cfg.line_min_aspect * np.maximum(width_m, 0.1)
    )
    if K < 2 or not line.any():
        return parent.astype(np.int64)
    li = np.flatnonzero(line)
    c, s = np.cos(yaw_rad[li]), np.sin(yaw_rad[li])
    d = center_xy[None, :, :] - center_xy[li, None, :]  # (L, K, 2)
    along = np.abs(d[..., 0] * c[:, None] + d[..., 1] * s[:, None])
    across = np.abs(-d[..., 0] * s[:, None] + d[..., 1] * c[:, None])
    turn = np.abs((yaw_rad[None, :] - yaw_rad[li, None] + np.pi / 2) % np.pi - np.pi / 2)
    slack = cfg.line_per_m * np.minimum(range_m[li, None], range_m[None, :])
    gap = along - 0.5 * (length_m[li, None] + length_m[None, :])
    # a piece of a line is thin (a person or a car beside a wall is not a piece of it); a long
    # one runs along it, a short one (a corner's return face, too) may turn
    along_line = (width_m[None, :] <= cfg.line_thick_m) & (
        (length_m[None, :] < 2.0) | (turn <= np.radians(cfg.line_max_turn_deg))
    )
    ok = (across <= cfg.line_offset_m + slack) & (gap <= cfg.line_gap_m + slack) & along_line
    ok[np.arange(li.size), li] = False
    for a, b in zip(*np.nonzero(ok), strict=True):
        ra, rb = _root(parent, int(li[a])), _root(parent, int(b))
        parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([_root(parent, k) for k in range(K)])
    _, new = np.unique(roots, return_inverse=True)
    return new.astype(np.int64)


def merge_grazing(
    center_xy: np.ndarray,
    width_m: np.ndarray,
    top_z_m: np.ndarray,
    sensor_xy: np.ndarray,
    col_step_rad: float,
    config: SegmentConfig | None = None,
) -> np.ndarray:
    """Faces seen at a grazing angle: (K,) int64 new label of each of K segments (0..K'-1, in
    order of first appearance), the pieces of one such face sharing a label.

    Along a row the returns of a face at incidence ``a`` lie ``r * dtheta / sin(a)`` apart, so
    below about 10 degrees neighbouring columns are too far apart to join and the face breaks
    into narrow vertical strips, each a column or two of returns, that follow each other along
    the line of sight. Strips that are thin, next to each other in azimuth and displaced along
    the ray are one face. A person or a car in front of a wall is not thin, and a post in
    front of one is a single strip whose top differs from the wall's.

    center_xy (K, 2) world m footprint centres, width_m (K,) extents across their long axes,
    top_z_m (K,) highest points (world z, m), sensor_xy (2,) world m, col_step_rad the
    egosphere's column step (rad).
    """
    cfg = config or SegmentConfig()
    K = center_xy.shape[0]
    parent = np.arange(K)
    thin = np.flatnonzero(width_m <= cfg.graze_thick_m)
    if thin.size < 2:
        return parent.astype(np.int64)
    c = center_xy[thin] - sensor_xy[None, :]
    r = np.hypot(c[:, 0], c[:, 1])
    az = np.arctan2(c[:, 1], c[:, 0])
    d_az = np.abs((az[:, None] - az[None, :] + np.pi) % (2 * np.pi) - np.pi)
    d = c[None, :, :] - c[:, None, :]  # (T, T, 2) from a to b
    dist = np.hypot(d[..., 0], d[..., 1])
    mid = 0.5 * (c[:, None, :] + c[None, :, :])
    ray = mid / np.maximum(np.hypot(mid[..., 0], mid[..., 1]), 1e-9)[..., None]
    along = np.abs((d * ray).sum(axis=-1))
    near = np.minimum(r[:, None], r[None, :])
    ok = (
        (d_az <= cfg.graze_cols * col_step_rad)
        & (along >= np.cos(np.radians(cfg.graze_max_deg)) * dist)
        & (dist <= cfg.graze_gap_m + cfg.graze_gap_per_m * near)
        & (np.abs(top_z_m[thin, None] - top_z_m[None, thin]) <= cfg.graze_dz_m)
    )
    # nearest pairs first; a join stands only if the face stays one line (a chain of strips
    # must not wander off the face onto whatever lies behind it along the same rays)
    a_i, b_i = np.nonzero(np.triu(ok, 1))
    members = {int(k): [int(k)] for k in thin}
    for n in np.argsort(dist[a_i, b_i], kind="stable"):
        ra, rb = _root(parent, int(thin[a_i[n]])), _root(parent, int(thin[b_i[n]]))
        if ra == rb:
            continue
        joined = members[ra] + members[rb]
        if _off_line_m(center_xy[joined]) > cfg.graze_thick_m:
            continue
        lo, hi = min(ra, rb), max(ra, rb)
        parent[hi] = lo
        members[lo] = joined
    roots = np.array([_root(parent, k) for k in range(K)])
    _, new = np.unique(roots, return_inverse=True)
    return new.astype(np.int64)


def _off_line_m(xy: np.ndarray) -> float:
    """Largest distance (m) of the points ``xy`` (N, 2) from their best-fitting line."""
    d = xy - xy.mean(axis=0)
    if len(d) < 3:
        return 0.0
    _, _, vt = np.linalg.svd(d, full_matrices=False)
    return float(np.abs(d @ vt[1]).max())


def _root(parent: np.ndarray, k: int) -> int:
    while parent[k] != k:
        parent[k] = parent[parent[k]]
        k = int(parent[k])
    return k


def range_edges(
    range_m: np.ndarray, valid: np.ndarray, config: SegmentConfig | None = None
) -> np.ndarray:
    """Level-2 edge pixels: (H, W) bool where the range jumps to a right or lower neighbour
    (the nearer side of the jump is the edge: it is the occluding boundary); ``range_m``
    (H, W) metres, ``valid`` (H, W) bool, jumps of ``edge_jump_m + edge_jump_frac * range``.
    A compiled pass (:func:`sp.lists.range_jump_edges`, with the level-2 primitives);
    :func:`sp.lists.range_jump_edges_reference` is the numpy form it equals."""
    from sp.lists import range_jump_edges  # sp.lists does not import this module: no cycle

    cfg = config or SegmentConfig()
    return range_jump_edges(range_m, valid, cfg.edge_jump_m, cfg.edge_jump_frac)

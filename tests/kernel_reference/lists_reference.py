"""Numpy oracles of the compiled level-2 passes of :mod:`sp.lists` (tests only).

:func:`block_moments_reference` is the oracle of :func:`sp.lists.block_moments` (one
bincount per moment), :func:`list_slots_reference` of :func:`sp.lists.list_slots` (and of the
slots of :func:`sp.lists.list_slots_and_sums`), :func:`list_sums_reference` of
:func:`sp.lists.list_sums` (bincounts: another summation order, equal to rounding). The range
edges' numpy form, :func:`sp.lists.range_jump_edges_reference`, stays in the engine: the
compiled pass falls back to it for other dtypes.
"""

from __future__ import annotations

import numpy as np

from sp.lists import ListKind, _moments_init, edge_branches, vertices


def block_moments_reference(xyz: np.ndarray, mask: np.ndarray, bh: int, bw: int) -> np.ndarray:
    """Oracle of :func:`sp.lists.block_moments` in plain numpy (one bincount per moment)."""
    H, W = mask.shape
    nbc = -(-W // bw)
    nbr = -(-H // bh)
    rows, cols = np.nonzero(mask)
    b = (rows // bh) * nbc + cols // bw
    p = xyz[rows, cols].astype(np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    B = nbr * nbc
    out = _moments_init(nbr, nbc)
    terms = [np.ones_like(x), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z]
    for k, t in enumerate(terms):
        out[:, k] = np.bincount(b, weights=t, minlength=B)
    np.minimum.at(out[:, 10], b, z)
    np.maximum.at(out[:, 11], b, z)
    return out


def list_slots_reference(
    owner: np.ndarray,
    range_edge: np.ndarray,
    brightness_edge: np.ndarray,
    patch: np.ndarray,
    lut: np.ndarray,
    list_ids: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Oracle of :func:`sp.lists.list_slots` in plain numpy."""
    branches = edge_branches(range_edge | brightness_edge)
    kind = np.full(owner.shape, -1, dtype=np.int64)
    kind[patch] = ListKind.SURFACE_PATCH
    kind[brightness_edge] = ListKind.BRIGHTNESS_EDGE
    kind[range_edge] = ListKind.RANGE_EDGE
    kind[vertices(branches)] = ListKind.VERTEX
    on = (kind >= 0) & (owner >= 0)
    key = owner * len(ListKind) + kind
    inside = on & (key < lut.size)
    slots = np.full(owner.shape, -1, dtype=np.int64)
    slots[inside] = lut[key[inside]]
    wait = on & (slots < 0)
    slots[wait] = -2 - key[wait]
    ids = np.full(owner.shape, -1, dtype=np.int64)
    ids[slots >= 0] = list_ids[slots[slots >= 0]]
    return slots, ids, branches, np.unique(key[wait])


def list_sums_reference(
    slot: np.ndarray,
    range_m: np.ndarray,
    intensity: np.ndarray,
    edge: np.ndarray,
    branches: np.ndarray,
    n_slots: int,
) -> np.ndarray:
    """Oracle of :func:`sp.lists.list_sums` in plain numpy (bincounts)."""
    W = slot.shape[1]
    pix = np.flatnonzero(slot.reshape(-1) >= 0)
    s = slot.reshape(-1)[pix]
    r, c = np.divmod(pix, W)
    br = branches[r, c].astype(np.float64)
    rf, cf = r.astype(np.float64), c.astype(np.float64)
    terms = [
        np.ones(pix.size),
        _finite_or_zero(range_m[r, c].astype(np.float64)),
        _neighbour_step(range_m.astype(np.float64), r, c, _ALONG_ROW),
        _neighbour_step(intensity.astype(np.float64), r, c),
        edge[r, c].astype(np.float64),
        ((br == 1) | (br >= 3)).astype(np.float64),
        br,
        rf,
        cf,
        rf * rf,
        cf * cf,
        rf * cf,
    ]
    return np.stack([np.bincount(s, weights=t, minlength=n_slots) for t in terms], axis=1)


def _finite_or_zero(x: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(x), x, 0.0)


_ALONG_ROW = ((0, 1), (0, -1))
_FOUR = ((0, 1), (0, -1), (1, 0), (-1, 0))


def _neighbour_step(
    img: np.ndarray, r: np.ndarray, c: np.ndarray, offsets: tuple = _FOUR
) -> np.ndarray:
    """(P,) largest |img[p] - img[neighbour]| over the neighbours ``offsets`` (row, column
    steps) of pixels (r, c); columns wrap round (the egosphere is closed in azimuth), rows stop
    at the border; NaN and infinite neighbours are skipped (0 when none)."""
    H, W = img.shape
    v = img[r, c]
    out = np.zeros(r.size)
    for dr, dc in offsets:
        rr = np.clip(r + dr, 0, H - 1)
        with np.errstate(invalid="ignore"):  # inf - inf: an empty pixel, skipped
            d = np.abs(img[rr, (c + dc) % W] - v)
        out = np.fmax(out, np.where(np.isfinite(d), d, 0.0))
    return out

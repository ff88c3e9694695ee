"""Numpy oracles of the compiled crease passes of :mod:`sp.surfaces` (tests only).

:func:`near_blocks_reference` is the oracle of :func:`sp.surfaces.near_blocks` (one shifted
comparison of the block grid per offset: the same pairs, another order),
:func:`crease_pixels_reference` of :func:`sp.surfaces.crease_pixels` (the candidate pixels
expanded, then filtered: the same output), and :func:`find_creases_reference` is
:func:`sp.surfaces.find_creases` with both passes in numpy.
:func:`foot_rise_deg_reference` is :func:`sp.level3_surfaces.foot_rise_deg` with the walks
up the columns in numpy, all feet in step.
"""

from __future__ import annotations

from typing import Any
from unittest import mock

import numpy as np

from sp import surfaces


def near_blocks_reference(block_label: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Oracle of :func:`sp.surfaces.near_blocks` (one shifted comparison of the grid per offset)."""
    nbr, nbc = block_label.shape
    idx = np.arange(nbr * nbc).reshape(nbr, nbc)
    offsets = [(0, dc) for dc in range(1, gap + 1)]
    offsets += [(dr, dc) for dr in range(1, gap + 1) for dc in range(-gap, gap + 1)]
    out_i, out_j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for dr, dc in offsets:
        if dr >= nbr or 2 * abs(dc) > nbc:
            continue
        a = block_label[: nbr - dr]
        b = np.roll(block_label, -dc, axis=1)[dr:]
        hit = (a >= 0) & (b >= 0) & (a != b)
        out_i.append(idx[: nbr - dr][hit])
        out_j.append(np.roll(idx, -dc, axis=1)[dr:][hit])
    return np.concatenate(out_i), np.concatenate(out_j)


def crease_pixels_reference(
    pair: np.ndarray,
    blk: np.ndarray,
    n_block_cols: int,
    block: tuple[int, int],
    label: np.ndarray,
    free: np.ndarray,
    xyz: np.ndarray,
    id_a: np.ndarray,
    id_b: np.ndarray,
    p0: np.ndarray,
    u: np.ndarray,
    tol_m: float,
    tol_per_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Oracle of :func:`sp.surfaces.crease_pixels` (the candidate pixels expanded, then
    filtered)."""
    H, W = label.shape
    bh, bw = block
    br, bc = np.divmod(blk, n_block_cols)
    pr = (br[:, None] * bh + np.arange(bh).repeat(bw)[None, :]).reshape(-1)
    pc = (bc[:, None] * bw + np.tile(np.arange(bw), bh)[None, :]).reshape(-1)
    q = np.repeat(pair, bh * bw)
    ok = (pr < H) & (pc < W)
    px, q = pr[ok] * W + pc[ok], q[ok]
    own = label.reshape(-1)[px]
    ok = (own == id_a[q]) | (own == id_b[q]) | ((own < 0) & free.reshape(-1)[px])
    px, q = px[ok], q[ok]
    p = xyz.reshape(-1, 3)[px]
    d = p - p0[q]
    tol2 = np.maximum(tol_m**2, tol_per_m**2 * np.einsum("ij,ij->i", p, p))
    with np.errstate(invalid="ignore"):
        on = np.einsum("ij,ij->i", d, d) - np.einsum("ij,ij->i", d, u[q]) ** 2 <= tol2
    return px[on].astype(np.int64), q[on].astype(np.int64)


def find_creases_reference(*args: Any, **kwargs: Any) -> surfaces.Creases:
    """:func:`sp.surfaces.find_creases` (same arguments) with its two compiled passes replaced
    by their oracles for the call (one place defines the rest); not for use from threads."""
    with (
        mock.patch.object(surfaces, "near_blocks", near_blocks_reference),
        mock.patch.object(surfaces, "crease_pixels", crease_pixels_reference),
    ):
        return surfaces.find_creases(*args, **kwargs)


def _next_return_reference(
    has: np.ndarray, i: np.ndarray, j: np.ndarray, step: int, gap: int
) -> np.ndarray:
    """(n,) int64 row of the next return from pixels (i, j) ((n,) int64 each) along their
    column in ``has`` (H, W) bool, ``step`` = +1 down or -1 up, across at most ``gap`` rows
    without one; -1 where there is none (or ``i`` is -1)."""
    H = has.shape[0]
    out = np.full(i.shape, -1, dtype=np.int64)
    for k in range(gap + 1, 0, -1):  # the nearest row wins: written last
        r = i + step * k
        inside = (i >= 0) & (r >= 0) & (r < H)
        hit = inside & has[np.clip(r, 0, H - 1), j]
        out = np.where(hit, r, out)
    return out


def foot_rise_deg_reference(
    labels: np.ndarray,
    xyz_g: np.ndarray,
    has_return: np.ndarray,
    ground: np.ndarray,
    n_segments: int,
    row_gap: int,
    max_chord_m: float,
    rise_m: float,
    max_rows: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Oracle of :func:`sp.level3_surfaces.foot_rise_deg`: every foot's walk up its column
    in step, vectorised over the feet (numpy)."""
    i_s, j_s = np.nonzero(labels >= 0)
    below = _next_return_reference(has_return, i_s, j_s, +1, row_gap)
    # the segment's feet: its pixels whose next return down is ground
    foot = below >= 0
    foot[foot] = ground[below[foot], j_s[foot]]
    i_f, j_f, i_g = i_s[foot], j_s[foot], below[foot]
    lab = labels[i_f, j_f]

    def hr_z(i: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = xyz_g[i, j_f]
        return np.hypot(p[:, 0], p[:, 1]), p[:, 2]

    def step_m(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        return np.hypot(b[0] - a[0], b[1] - a[1])

    at_foot = hr_z(i_f)
    alive = step_m(hr_z(i_g), at_foot) <= max_chord_m
    top, at_top = i_f.copy(), at_foot
    at_first = at_foot  # the walk's first step up (where it counts, the walk took one)
    reached = np.zeros(i_f.size, dtype=bool)
    ended = np.zeros(i_f.size, dtype=bool)  # the segment's top in this column came first
    for step in range(max_rows):
        walking = alive & ~reached & ~ended
        if not walking.any():
            break
        nxt = _next_return_reference(has_return, np.where(walking, top, -1), j_f, -1, row_gap)
        own = (nxt >= 0) & (labels[np.maximum(nxt, 0), j_f] == lab)
        ended |= walking & ~own
        at_next = hr_z(np.maximum(nxt, 0))
        close = step_m(at_top, at_next) <= max_chord_m
        alive &= ~(walking & own & ~close)
        move = walking & own & close
        top = np.where(move, nxt, top)
        at_top = (np.where(move, at_next[0], at_top[0]), np.where(move, at_next[1], at_top[1]))
        if step == 0:
            at_first = at_top
        reached |= move & (at_top[1] - at_foot[1] >= rise_m)
    rise = at_top[1] - at_foot[1]
    # a segment lower than rise_m above its foot (the crest of a bank whose flank is ground)
    # counts from half of it
    counted = alive & (reached | (ended & (rise >= 0.5 * rise_m)))

    def angle_to(at: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        return np.degrees(np.arctan2(at[1] - at_foot[1], at[0] - at_foot[0]))

    # a bank is gentle in both, a dome or a rounded car body steep in one of them
    angle = np.maximum(angle_to(at_first), angle_to(at_top))
    lab, angle = lab[counted], angle[counted]
    count = np.bincount(lab, minlength=n_segments)
    median = np.full(n_segments, np.nan)
    if lab.size:
        order = np.lexsort((angle, lab))
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        has = count > 0
        lo = start[has] + (count[has] - 1) // 2
        hi = start[has] + count[has] // 2
        median[has] = 0.5 * (angle[order][lo] + angle[order][hi])
    return median, count

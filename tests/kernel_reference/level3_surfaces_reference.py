"""Numpy oracle of the compiled walk of :mod:`sp.level3_surfaces` (tests only).

:func:`foot_rise_deg_reference` is :func:`sp.level3_surfaces.foot_rise_deg` with the walks up
the columns in numpy, all feet in step (the form the engine ran before the walk was compiled).
"""

from __future__ import annotations

import numpy as np


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

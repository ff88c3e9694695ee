"""Compiled climb of the plain (unmasked) correlation search of :mod:`maps.pyramid` (numba).

:func:`climb` is the loop form of :func:`maps.pyramid._climb_steps` with its ``_Window`` for
two images without masks: the same windows (every pixel of ``mov`` whose partner in ``ref`` exists
for every offset within the window's reach of the offset it was built at), the same 9-offset
steps, stopping rule and search limits. The numpy form serves the masked search and is the
reference the tests hold this to (``register_reference`` in ``tests/kernel_reference``).

What differs is only how the sums are taken, all in one pass each and no Python call per
offset: a window's sums and sums of squares of ``ref`` for all its offsets by sliding row and
column sums (float64), and each cross sum as a float32 dot product of the centred template
with the shifted ``ref`` window (reassociated into vector lanes, as a BLAS dot product is).
Only the offsets the climb asks for get a cross sum. Images are (H, W) float32, C order.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# the window could not be built: the offset +- reach leaves no overlap (see pyramid._Window)
NO_OVERLAP = -1


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _window_sums(ref, r0, r1, c0, c1, cr, cc, reach, s, ss):
    """Sum and sum of squares (float64) of ``ref``'s window for every offset ``(dr, dc)``
    within ``reach`` of ``(cr, cc)``: ``s[dr - cr + reach, dc - cc + reach]`` over
    ``ref[r0 - dr : r1 - dr, c0 - dc : c1 - dc]``, by sliding row sums along the columns and
    then the rows."""
    k = 2 * reach + 1
    h = r1 - r0
    w = c1 - c0
    top = r0 - cr - reach  # first ref row any offset's window touches
    left = c0 - cc - reach
    n_rows = h + 2 * reach
    row_s = np.empty((n_rows, k))
    row_ss = np.empty((n_rows, k))
    for y in range(n_rows):
        row = ref[top + y, left : left + w]  # the leftmost window: offset dc = cc + reach
        a = 0.0
        b = 0.0
        for x in range(w):
            v = np.float64(row[x])
            a += v
            b += v * v
        row_s[y, k - 1] = a
        row_ss[y, k - 1] = b
        for j in range(k - 2, -1, -1):  # each smaller dc moves the window one column right
            x_out = left + (k - 2 - j)
            x_in = x_out + w
            v_out = np.float64(ref[top + y, x_out])
            v_in = np.float64(ref[top + y, x_in])
            a += v_in - v_out
            b += v_in * v_in - v_out * v_out
            row_s[y, j] = a
            row_ss[y, j] = b
    for j in range(k):
        a = 0.0
        b = 0.0
        for y in range(h):
            a += row_s[y, j]
            b += row_ss[y, j]
        s[k - 1, j] = a
        ss[k - 1, j] = b
        for i in range(k - 2, -1, -1):
            y_out = k - 2 - i
            y_in = y_out + h
            a += row_s[y_in, j] - row_s[y_out, j]
            b += row_ss[y_in, j] - row_ss[y_out, j]
            s[i, j] = a
            ss[i, j] = b


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _cross(ref, t, r0, c0, dr, dc):
    """Sum of ``t`` (h, w) float32 times ``ref[r0 - dr :, c0 - dc :]``'s (h, w) window: each
    row's products summed in float32 vector lanes, the rows in float64."""
    h, w = t.shape
    acc = 0.0
    for y in range(h):
        t_row = t[y]
        r_row = ref[r0 - dr + y, c0 - dc : c0 - dc + w]
        a = np.float32(0.0)
        for x in range(w):
            a += t_row[x] * r_row[x]
        acc += a
    return acc


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _build(ref, mov, cr, cc, reach, flat_std, table, done, s, ss, bounds):
    """The window for offsets within ``reach`` of ``(cr, cc)``: its bounds ``(r0, r1, c0,
    c1)`` in ``mov`` into ``bounds``, its centred float32 template (returned; empty for no
    overlap), the norm and ``ref``'s window sums; ``table`` / ``done`` cleared (NaN and
    done everywhere when the template has no texture). Returns ``(template, t_norm, ops)``,
    ``bounds[0]`` set to ``NO_OVERLAP`` when there is none."""
    h, w = mov.shape
    r0 = max(0, cr + reach)
    r1 = min(h, ref.shape[0] + cr - reach)
    c0 = max(0, cc + reach)
    c1 = min(w, ref.shape[1] + cc - reach)
    if r1 - r0 < 2 or c1 - c0 < 2:
        bounds[0] = NO_OVERLAP
        return np.empty((0, 0), np.float32), 0.0, 0
    bounds[0], bounds[1], bounds[2], bounds[3] = r0, r1, c0, c1
    n = (r1 - r0) * (c1 - c0)
    total = 0.0
    for y in range(r0, r1):
        row = mov[y, c0:c1]
        for x in range(c1 - c0):
            total += np.float64(row[x])
    mean = np.float32(total / n)
    t = np.empty((r1 - r0, c1 - c0), np.float32)
    sq = 0.0
    for y in range(r0, r1):
        row = mov[y, c0:c1]
        t_row = t[y - r0]
        for x in range(c1 - c0):
            v = row[x] - mean
            t_row[x] = v
            sq += np.float64(v) * np.float64(v)
    t_norm = math.sqrt(sq)
    k = 2 * reach + 1
    for i in range(k):
        for j in range(k):
            table[i, j] = np.nan
            done[i, j] = False
    if t_norm < flat_std * math.sqrt(n):  # no texture: every offset correlates as NaN
        for i in range(k):
            for j in range(k):
                done[i, j] = True
        return t, t_norm, 0
    _window_sums(ref, r0, r1, c0, c1, cr, cc, reach, s, ss)
    region = (r1 - r0 + 2 * reach) * (c1 - c0 + 2 * reach)
    return t, t_norm, n + region


@numba.njit(cache=True, nogil=True, error_model="numpy")
def climb(
    ref, mov, start_r, start_c, extent_r, extent_c, reach, max_steps, min_gain, flat_std,
    surface, out,
):  # fmt: skip
    """The 9-offset climb of :func:`maps.pyramid._climb` from ``(start_r, start_c)`` (already
    within ``+-extent``), with windows of ``reach``. Writes the (3, 3) correlation around the
    peak into ``surface`` (NaN outside the extent) and ``out = (peak_r, peak_c, pinned,
    multiply_adds, overlap_r, overlap_c)`` (int64; ``overlap`` the offset a window could not
    be built at, when ``pinned`` is ``NO_OVERLAP``); returns the window's coverage of
    ``mov``."""
    k = 2 * reach + 1
    table = np.empty((k, k))
    done = np.zeros((k, k), np.bool_)
    s = np.empty((k, k))
    ss = np.empty((k, k))
    bounds = np.zeros(4, np.int64)
    cr, cc = start_r, start_c
    wr, wc = cr + reach, cc  # the offset the window was built at (none yet: out of reach)
    t = np.empty((0, 0), np.float32)
    t_norm = 0.0
    ops = w_ops = n = 0
    cover = flat2n = 0.0
    for _ in range(max_steps):
        if max(abs(cr - wr), abs(cc - wc)) > reach - 1:  # not covered: a new window here
            ops += w_ops
            t, t_norm, w_ops = _build(ref, mov, cr, cc, reach, flat_std, table, done, s, ss, bounds)
            if bounds[0] == NO_OVERLAP:
                out[2], out[4], out[5] = NO_OVERLAP, cr, cc
                return 0.0
            wr, wc = cr, cc
            n = t.shape[0] * t.shape[1]
            cover = n / (mov.shape[0] * mov.shape[1])
            flat2n = flat_std * flat_std * n
        r0, c0 = bounds[0], bounds[2]
        pinned = False
        best = -1
        best_v = 0.0
        for a in range(3):
            for b in range(3):
                dr = cr + a - 1
                dc = cc + b - 1
                i = dr - wr + reach
                j = dc - wc + reach
                if not done[i, j]:
                    var = ss[i, j] - s[i, j] * s[i, j] / n
                    if var > flat2n:
                        cross = _cross(ref, t, r0, c0, dr, dc)
                        table[i, j] = cross / (t_norm * math.sqrt(max(var, 0.0)))
                    w_ops += n
                    done[i, j] = True
                v = table[i, j]
                if abs(dr) > extent_r or abs(dc) > extent_c:  # beyond the search limit
                    pinned = True
                    v = np.nan
                surface[a, b] = v
                if v == v and (best < 0 or v > best_v):
                    best = 3 * a + b
                    best_v = v
        if best < 0:
            out[0], out[1], out[2], out[3] = cr, cc, 0, ops + w_ops
            return cover
        centre = surface[1, 1]
        centre_value = centre if math.isfinite(centre) else -np.inf
        if best == 4 or best_v <= centre_value + min_gain:
            out[0], out[1], out[2], out[3] = cr, cc, 1 if pinned else 0, ops + w_ops
            return cover
        cr += best // 3 - 1
        cc += best % 3 - 1
    out[0], out[1], out[2], out[3] = cr, cc, 1, ops + w_ops  # out of steps: pinned
    return cover

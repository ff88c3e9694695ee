"""Compiled single-pass kernels of point fusion and ray casting (numba).

Each kernel is the loop form of a numpy step in :mod:`maps.fusion`, which stays the plain
reference the tests compare these kernels against (``FusionConfig(compiled=False)``):

* :func:`bin_points`: cleaning (NaN/inf or non-positive variance dropped and counted), the
  point's cell, the window test, each touched cell's row (first-seen order) and lowest point;
  one pass over the points;
* :func:`ground_gate`: the obstacle gate of each cell with points (reference 001, 4.5.3
  hypothesize and test); one pass over the touched cells and their 8 neighbours;
* :func:`sum_points`: per-cell inverse-variance sums of the ground points, obstacle counts and
  highest point; the second pass over the points;
* :func:`merge_child`: a finer level's per-cell sums into this level's rows;
* :func:`storage_order`: the touched cells' rows by storage index, the order in which the
  per-cell passes walk the layers' memory;
* :func:`apply_cells`: the per-cell Kalman update (001, 4.5.4 eq. 4.3), weighted moments,
  min / max, occupancy log-odds and last-seen; one pass over the touched cells;
* :func:`cast_rays`: 2-D free-space traversal of each beam (Amanatides and Woo's grid walk);
* :func:`terrain`: slope, step height and traversability of a window, one pass over its cells
  (``terrain_layers_reference``, a test oracle, is its numpy form).

Storage indices are flat toroidal indices ``(iy % size) * size + ix % size`` (see
:mod:`maps.level`). Dense per-level scratch is never cleared: a cell's entry counts only when
its ``tag`` holds the current sweep number in its high 32 bits (and its row among the
sweep's touched cells in the low 32). Nothing is compiled at import: the first call of
each kernel compiles it (seconds) and caches it on disk.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_BIG = 1.7976931348623157e308  # np.nan_to_num's value for +inf (float64 max)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _variance(xyz, var, mode, origin, s0, k, i):
    """Variance (m^2) of point ``i``: given per point (mode 0), one scalar (mode 1), or from
    its range to ``origin`` as ``(s0 + k r)^2`` (mode 2, :func:`maps.fusion.range_variance`)."""
    if mode == 0:
        return var[i]
    if mode == 1:
        return var[0]
    dx = xyz[i, 0] - origin[0]
    dy = xyz[i, 1] - origin[1]
    dz = xyz[i, 2] - origin[2]
    s = s0 + k * math.sqrt(dx * dx + dy * dy + dz * dz)
    return s * s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def bin_points(
    xyz, var, mode, origin, s0, k, idx, use_idx, clean,
    res, ox, oy, size, tag, sweep, cells, cix, ciy, z_lo, point_row, rest,
):  # fmt: skip
    """One pass over points ``xyz`` (N, 3) float64 world metres (all of them, or the indices
    ``idx`` when ``use_idx``): each point's row among the sweep's touched cells of a level.

    With ``clean``, points with a NaN/inf coordinate or variance, or a variance <= 0, are
    dropped. Writes ``point_row[j]`` (the j-th visited point's row, -1 if dropped or outside the
    window), ``cells[r]`` (flat storage index of row r), ``z_lo[r]`` (lowest z, m) and ``rest``
    (indices of the kept points outside the window). Returns ``(rows, n_rest, n_dropped,
    z_sum)``, ``z_sum`` the sum of the kept points' z (m).
    """
    n_iter = idx.shape[0] if use_idx else xyz.shape[0]
    m = 0
    n_rest = 0
    n_drop = 0
    z_sum = 0.0
    mask = size - 1
    pow2 = (size & mask) == 0
    for j in range(n_iter):
        i = idx[j] if use_idx else j
        x = xyz[i, 0]
        y = xyz[i, 1]
        z = xyz[i, 2]
        if clean:
            v = _variance(xyz, var, mode, origin, s0, k, i)
            if not (math.isfinite(x + y + z + v) and v > 0.0):
                n_drop += 1
                point_row[j] = -1
                continue
            z_sum += z
        fx = math.floor(x / res)
        fy = math.floor(y / res)
        if not (abs(fx) < 4.0e18 and abs(fy) < 4.0e18):  # beyond int64: outside any window
            point_row[j] = -1
            rest[n_rest] = i
            n_rest += 1
            continue
        ix = np.int64(fx)
        iy = np.int64(fy)
        cx = ix - ox
        cy = iy - oy
        if cx < 0 or cx >= size or cy < 0 or cy >= size:
            point_row[j] = -1
            rest[n_rest] = i
            n_rest += 1
            continue
        if pow2:
            flat = (iy & mask) * size + (ix & mask)
        else:
            flat = (iy % size) * size + ix % size
        t = tag[flat]
        if (t >> 32) != sweep:
            tag[flat] = (sweep << 32) | m
            cells[m] = flat
            cix[m] = ix
            ciy[m] = iy
            z_lo[m] = z
            point_row[j] = m
            m += 1
        else:
            r = t & 0xFFFFFFFF
            point_row[j] = r
            z_lo[r] = min(z_lo[r], z)  # no branch: the comparison is a coin toss
    return m, n_rest, n_drop, z_sum


@numba.njit(cache=True, nogil=True, error_model="numpy")
def storage_order(cells, mark, order):
    """Rows of ``cells`` (M,) distinct flat storage indices, into ``order`` (M,) by storage
    index: the per-cell passes then walk each layer's memory forwards, a cache line serving
    every touched cell it holds (in scan order a sweep's cells are scattered over the layers,
    and in a full node cycle the layers have left the cache). ``mark`` (size*size) int32 must
    hold -1 and is left so. Returns the rows ordered: fewer than M if cells repeat."""
    for r in range(cells.shape[0]):
        mark[cells[r]] = r
    k = 0
    for c in range(mark.shape[0]):
        r = mark[c]
        if r >= 0:
            order[k] = r
            k += 1
            mark[c] = -1
    return k


@numba.njit(cache=True, nogil=True, error_model="numpy")
def ground_gate(
    m, cells, z_lo, z_ref, elevation, elevation_var, dense_z_lo, size, ox, oy,
    obstacle_h, allowance, gate, stale, order,
):  # fmt: skip
    """Obstacle gate ``gate[r]`` (m, relative to ``z_ref``) and refuted flag ``stale[r]`` of
    the first ``m`` rows (cells with raw points; ``z_lo`` absolute metres), exactly as
    :func:`maps.fusion._ground_gate`: the estimate + 3 sigma, or for a new or refuted cell
    ``min(own lowest, lowest 8-neighbour + allowance)``, plus ``obstacle_h``.
    ``dense_z_lo`` (size*size) must hold +inf and is left so. Rows are visited in ``order``
    (:func:`storage_order`; empty: row order)."""
    ordered = order.shape[0] == m
    mask = size - 1
    pow2 = (size & mask) == 0
    for j in range(m):
        r = order[j] if ordered else j
        z_lo[r] = z_lo[r] - z_ref
        dense_z_lo[cells[r]] = z_lo[r]
    for j in range(m):
        r = order[j] if ordered else j
        c = cells[r]
        e = np.float64(elevation[c]) - z_ref
        sigma = math.sqrt(np.float64(elevation_var[c]))
        if math.isnan(sigma):
            sigma = 0.0
        elif math.isinf(sigma):
            sigma = _BIG
        spread = 3.0 * sigma
        known = math.isfinite(e)
        st = known and z_lo[r] < e - spread - obstacle_h
        stale[r] = st
        if known and not st:
            gate[r] = e + spread + obstacle_h
            continue
        srow = c // size
        scol = c - srow * size
        if pow2:  # a mask, not an integer division (floor modulo for negatives too)
            wrow = (srow - oy) & mask
            wcol = (scol - ox) & mask
        else:
            wrow = (srow - oy) % size
            wcol = (scol - ox) % size
        nb = np.inf
        for dr in range(-1, 2):
            if wrow + dr < 0 or wrow + dr >= size:
                continue
            nrow = srow + dr  # the neighbour's storage row, wrapped by a compare
            if nrow < 0:
                nrow += size
            elif nrow >= size:
                nrow -= size
            for dc in range(-1, 2):
                if (dr == 0 and dc == 0) or wcol + dc < 0 or wcol + dc >= size:
                    continue
                ncol = scol + dc
                if ncol < 0:
                    ncol += size
                elif ncol >= size:
                    ncol -= size
                nflat = nrow * size + ncol
                en = elevation[nflat]
                base = dense_z_lo[nflat] if math.isnan(en) else np.float64(en) - z_ref
                if base < nb:
                    nb = base
        ref = min(z_lo[r], nb + allowance)
        gate[r] = ref + obstacle_h
    for j in range(m):
        dense_z_lo[cells[order[j] if ordered else j]] = np.inf


@numba.njit(cache=True, nogil=True, error_model="numpy")
def sum_points(
    xyz, var, mode, origin, s0, k, idx, use_idx, point_row, z_ref, gate, m,
    w, wz, wzz, n, n_obs, z_hi,
):  # fmt: skip
    """Second pass over the points :func:`bin_points` visited (same ``idx``/``use_idx``):
    points at or below their cell's ``gate`` are ground and add ``1/var``, ``(z - z_ref)/var``,
    ``(z - z_ref)^2/var`` and 1 to ``w, wz, wzz, n`` of their row; the others add 1 to
    ``n_obs``. ``z_hi`` takes the highest ``z - z_ref`` of all. The first ``m`` rows are
    zeroed (``z_hi`` set to -inf) first."""
    for r in range(m):
        w[r] = 0.0
        wz[r] = 0.0
        wzz[r] = 0.0
        n[r] = 0
        n_obs[r] = 0
        z_hi[r] = -np.inf
    n_iter = point_row.shape[0]
    for j in range(n_iter):
        r = point_row[j]
        if r < 0:
            continue
        i = idx[j] if use_idx else j
        z = xyz[i, 2] - z_ref
        if z <= gate[r]:
            wi = 1.0 / _variance(xyz, var, mode, origin, s0, k, i)
            zi = wi * z
            w[r] += wi
            wz[r] += zi
            wzz[r] += zi * z
            n[r] += 1
        else:
            n_obs[r] += 1
        z_hi[r] = max(z_hi[r], z)  # no branch: the comparison is a coin toss


@numba.njit(cache=True, nogil=True, error_model="numpy")
def merge_child(
    m, c_ix, c_iy, c_w, c_wz, c_wzz, c_n, c_nobs, c_zmin, c_zmax, c_zref, scale,
    z_ref, res_ox, res_oy, size, tag, sweep, cells, cix, ciy,
    w, wz, wzz, n, n_obs, z_lo, z_hi,
):  # fmt: skip
    """Add a finer level's per-cell sums (``c_*``, its cells ``c_ix, c_iy`` at ``scale`` =
    child / this resolution, its sums centred on ``c_zref``) to the rows of the cell holding
    each child cell's centre, re-centred on ``z_ref``; new rows from ``m`` on. Child cells
    outside the window are skipped. Returns the new row count."""
    mask = size - 1
    pow2 = (size & mask) == 0
    cz = c_zref - z_ref
    for j in range(c_ix.shape[0]):
        ix = np.int64(math.floor((c_ix[j] + 0.5) * scale))
        iy = np.int64(math.floor((c_iy[j] + 0.5) * scale))
        if ix - res_ox < 0 or ix - res_ox >= size or iy - res_oy < 0 or iy - res_oy >= size:
            continue
        if pow2:
            flat = (iy & mask) * size + (ix & mask)
        else:
            flat = (iy % size) * size + ix % size
        if (tag[flat] >> 32) != sweep:
            tag[flat] = (sweep << 32) | m
            cells[m] = flat
            cix[m] = ix
            ciy[m] = iy
            z_lo[m] = np.inf
            z_hi[m] = -np.inf
            w[m] = 0.0
            wz[m] = 0.0
            wzz[m] = 0.0
            n[m] = 0
            n_obs[m] = 0
            m += 1
        r = tag[flat] & 0xFFFFFFFF
        cw = c_w[j]
        cwz = c_wz[j]
        w[r] += cw
        wz[r] += cwz + cw * cz
        wzz[r] += c_wzz[j] + 2.0 * cz * cwz + cw * cz * cz
        n[r] += c_n[j]
        n_obs[r] += c_nobs[j]
        lo = c_zmin[j] - z_ref
        if lo < z_lo[r]:
            z_lo[r] = lo
        hi = c_zmax[j] - z_ref
        if hi > z_hi[r]:
            z_hi[r] = hi
    return m


@numba.njit(cache=True, nogil=True, error_model="numpy")
def apply_cells(
    cells, w, wz, wzz, n, n_obs, z_min, z_max, reset, z_ref, t_ns,
    process_var, l_hit, l_miss, l_min, l_max, conf_var,
    elevation, elevation_var, elevation_min, elevation_max, count, obstacle_count,
    z_weight, z_mean, z_sq_dev_sum, roughness, occupancy, confidence, last_seen_ns, order,
):  # fmt: skip
    """Update the layers (flat storage views) of each batch cell, as :func:`maps.fusion.apply`:
    a refuted cell without ground now forgets its height; a cell with ground points gets the
    scalar Kalman update ``K = P / (P + R)``, ``x += K (z_bar - x)``, ``P = (1 - K) P`` with
    ``R = 1 / w``, ``z_bar = z_ref + wz / w`` (001, 4.5.4 eq. 4.3) and the weighted moment
    merge; every cell its min / max, obstacle count, occupancy log-odds and last-seen time.
    Cells are visited in ``order`` (:func:`storage_order`; empty: batch order)."""
    nan = np.nan
    m = cells.shape[0]
    ordered = order.shape[0] == m
    for j in range(m):
        r = order[j] if ordered else j
        c = cells[r]
        g = n[r] > 0
        rs = reset[r]
        if rs and not g:
            elevation[c] = nan
            elevation_var[c] = nan
            z_mean[c] = nan
            roughness[c] = nan
            z_weight[c] = 0.0
            z_sq_dev_sum[c] = 0.0
            count[c] = 0
        if g:
            R = 1.0 / w[r]
            z_bar = z_ref + wz[r] * R
            x = np.float64(elevation[c])
            P = np.float64(elevation_var[c]) + process_var
            if rs or not (math.isfinite(x) and math.isfinite(P)):
                x = z_bar
                P = R
            else:
                K = P / (P + R)
                x = x + K * (z_bar - x)
                P = (1.0 - K) * P
            elevation[c] = x
            elevation_var[c] = P
            confidence[c] = conf_var / (conf_var + P)
            w_b = w[r]
            mean_b = wz[r] / w_b
            m2_b = max(wzz[r] - wz[r] * mean_b, 0.0)
            mean_b = mean_b + z_ref
            w_a = z_weight[c]
            m2_a = z_sq_dev_sum[c]
            if rs:
                w_a = 0.0
                m2_a = 0.0
                count[c] = 0
            mean_a = z_mean[c] if w_a > 0 else mean_b
            ww = w_a + w_b
            delta = mean_b - mean_a
            m2 = m2_a + m2_b + delta * delta * w_a * w_b / ww
            z_weight[c] = ww
            z_mean[c] = mean_a + delta * w_b / ww
            z_sq_dev_sum[c] = m2
            roughness[c] = math.sqrt(m2 / ww)
            count[c] += np.int32(n[r])
        lo = np.float64(elevation_min[c])
        elevation_min[c] = z_min[r] if math.isnan(lo) else min(lo, z_min[r])
        hi = np.float64(elevation_max[c])
        elevation_max[c] = z_max[r] if math.isnan(hi) else max(hi, z_max[r])
        obstacle_count[c] += np.int32(n_obs[r])
        occ = np.float64(occupancy[c]) + (l_hit if n_obs[r] > 0 else l_miss)
        occupancy[c] = min(max(occ, l_min), l_max)
        last_seen_ns[c] = t_ns


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _walk(
    sx, sy, first, px, py, pz, qz, t_lim, res_ox, res_oy, size, free_h, stop_after,
    tag, sweep, ray_stamp, elevation, elevation_max, occupancy, l_miss, l_min,
):  # fmt: skip
    """Walk one beam over the grid from ``(sx, sy)`` (cell units; the beam at parameter
    ``t_lim`` of the way from the origin ``(px, py)`` to its point) back to the origin cell;
    the start cell counts only if ``first``. See :func:`cast_rays`; returns cells lowered."""
    run = 0  # cells in a row this sweep already settled (points or an earlier beam)
    mask = size - 1
    pow2 = (size & mask) == 0
    cx = np.int64(math.floor(sx))
    cy = np.int64(math.floor(sy))
    ix0 = np.int64(math.floor(px))
    iy0 = np.int64(math.floor(py))
    dx = px - sx  # walk direction, cell units; u in [0, 1] from start to origin
    dy = py - sy
    stx = 1 if dx > 0 else -1
    sty = 1 if dy > 0 else -1
    u_dx = abs(1.0 / dx) if dx != 0.0 else np.inf
    u_dy = abs(1.0 / dy) if dy != 0.0 else np.inf
    if dx > 0:
        u_x = (cx + 1 - sx) * u_dx
    elif dx < 0:
        u_x = (sx - cx) * u_dx
    else:
        u_x = np.inf
    if dy > 0:
        u_y = (cy + 1 - sy) * u_dy
    elif dy < 0:
        u_y = (sy - cy) * u_dy
    else:
        u_y = np.inf
    u_in = 0.0
    lowered = 0
    steps = abs(cx - ix0) + abs(cy - iy0)
    for step in range(steps + 1):
        u_out = min(u_x, u_y, 1.0)
        ux = cx - res_ox
        uy = cy - res_oy
        if (step > 0 or first) and ux >= 0 and ux < size and uy >= 0 and uy < size:
            if pow2:
                c = (cy & mask) * size + (cx & mask)
            else:
                c = (cy % size) * size + cx % size
            if (tag[c] >> 32) == sweep or ray_stamp[c] == sweep:
                run += 1
                if run == stop_after:
                    break
            else:
                run = 0
                z_beam = pz + (qz - pz) * t_lim * (1.0 - 0.5 * (u_in + u_out))
                ground = np.float64(elevation[c])
                if math.isnan(ground):
                    ground = qz
                top = np.float64(elevation_max[c])  # NaN (never a point there): no limit
                if z_beam - ground <= free_h and not z_beam > top:
                    ray_stamp[c] = sweep
                    occupancy[c] = max(np.float64(occupancy[c]) + l_miss, l_min)
                    lowered += 1
        if u_x < u_y:
            cx += stx
            u_in = u_x
            u_x += u_dx
        else:
            cy += sty
            u_in = u_y
            u_y += u_dy
    return lowered


@numba.njit(cache=True, nogil=True, error_model="numpy")
def cast_rays(
    xyz, idx, use_idx, origin, res, ox, oy, size, max_range, free_h, stop_after,
    tag, sweep, ray_stamp, start_stamp, start_beam, elevation, elevation_max, occupancy,
    l_miss, l_min,
):  # fmt: skip
    """Free space: walk beams over the grid (2-D, Amanatides and Woo) from their points back
    to ``origin`` (world metres) and lower the log-odds of each cell they cross before their
    end cell by ``l_miss`` (clamped at ``l_min``), once per sweep (``ray_stamp``). Skipped:
    cells holding points this sweep (``tag >> 32 == sweep``: their own hit / miss stands), cells
    outside the window, cells beyond ``max_range`` (m, horizontal) and cells the beam crosses
    more than ``free_h`` (m) above their ground (the elevation estimate, else the beam end's
    z): a beam high over a cell says nothing about a low obstacle there; and cells the beam
    crosses above the highest point ever seen there (``elevation_max``): it passed over
    whatever stands there, not through it.

    Of the beams that start their walk in one cell (they end there, or reach ``max_range``
    there) only the one with the lowest end is walked: from one origin through one cell, the
    others cross the same cells up to a cell's width (and no lower). A walk ends early after
    ``stop_after`` cells in a row (0: never) that this sweep has already settled (cells with
    points, cells an earlier beam lowered): it has entered ground the beams before it
    covered (the few cells beyond that the full walks would lower are not worth walking the
    rest of every beam). ``start_stamp`` / ``start_beam`` are dense
    (size*size) scratch. Returns the cells lowered.
    """
    n_iter = idx.shape[0] if use_idx else xyz.shape[0]
    mask = size - 1
    pow2 = (size & mask) == 0
    px = origin[0] / res
    py = origin[1] / res
    pz = origin[2]
    starts = np.empty(min(n_iter, size * size), dtype=np.int64)
    n_starts = 0
    lowered = 0
    for j in range(n_iter):  # pick one beam per start cell
        i = idx[j] if use_idx else j
        qx = xyz[i, 0] / res
        qy = xyz[i, 1] / res
        qz = xyz[i, 2]
        if not (math.isfinite(qx) and math.isfinite(qy) and math.isfinite(qz)):
            continue
        length = math.sqrt((qx - px) ** 2 + (qy - py) ** 2) * res  # horizontal metres
        if length == 0.0:
            continue
        t_lim = 1.0 if length <= max_range else max_range / length
        sx = px + t_lim * (qx - px)  # walk start: the point, or the beam at max range
        sy = py + t_lim * (qy - py)
        if not (abs(sx) < 4.0e18 and abs(sy) < 4.0e18):
            continue
        cx = np.int64(math.floor(sx))
        cy = np.int64(math.floor(sy))
        if cx - ox < 0 or cx - ox >= size or cy - oy < 0 or cy - oy >= size:
            lowered += _walk(
                sx, sy, t_lim < 1.0, px, py, pz, qz, t_lim, ox, oy, size, free_h, stop_after,
                tag, sweep, ray_stamp, elevation, elevation_max, occupancy, l_miss, l_min,
            )  # fmt: skip
            continue
        if pow2:
            c = (cy & mask) * size + (cx & mask)
        else:
            c = (cy % size) * size + cx % size
        if start_stamp[c] != sweep:
            start_stamp[c] = sweep
            start_beam[c] = i
            starts[n_starts] = c
            n_starts += 1
        elif qz < xyz[start_beam[c], 2]:
            start_beam[c] = i
    for k in range(n_starts):
        i = start_beam[starts[k]]
        qx = xyz[i, 0] / res
        qy = xyz[i, 1] / res
        qz = xyz[i, 2]
        length = math.sqrt((qx - px) ** 2 + (qy - py) ** 2) * res
        t_lim = 1.0 if length <= max_range else max_range / length
        sx = px + t_lim * (qx - px)
        sy = py + t_lim * (qy - py)
        lowered += _walk(
            sx, sy, t_lim < 1.0, px, py, pz, qz, t_lim, ox, oy, size, free_h, stop_after,
            tag, sweep, ray_stamp, elevation, elevation_max, occupancy, l_miss, l_min,
        )  # fmt: skip
    return lowered


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _grad(prev, centre, nxt, res):
    """Gradient along one axis: central where both neighbours are known, else one-sided."""
    g = (nxt - prev) / (2.0 * res)
    if math.isfinite(g):
        return g
    g = (nxt - centre) / res
    if math.isfinite(g):
        return g
    return (centre - prev) / res


@numba.njit(cache=True, nogil=True, error_model="numpy")
def terrain(
    e, rough, occ, res, max_slope, max_step, max_rough, occupied, slope, step, trav
):  # pragma: no cover
    """Terrain layers of a window, exactly as ``terrain_layers_reference`` (a test oracle): ``e``,
    ``rough``, ``occ`` (H, W) float64 elevation (m, NaN unknown), roughness (m), occupancy
    (log-odds); writes ``slope`` (rad), ``step`` (m), ``trav`` (0..1) (H, W) float32."""
    H, W = e.shape
    nan = np.nan
    for r in range(H):
        for c in range(W):
            z = e[r, c]
            if not math.isfinite(z):
                slope[r, c] = nan
                step[r, c] = nan
                trav[r, c] = nan
                continue
            left = e[r, c - 1] if c > 0 else nan
            right = e[r, c + 1] if c + 1 < W else nan
            down = e[r - 1, c] if r > 0 else nan
            up = e[r + 1, c] if r + 1 < H else nan
            gx = _grad(left, z, right, res)
            gy = _grad(down, z, up, res)
            fx = math.isfinite(gx)
            fy = math.isfinite(gy)
            if fx or fy:
                s = math.atan(math.hypot(gx if fx else 0.0, gy if fy else 0.0))
            else:
                s = nan
            st = nan
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    if (dr == 0 and dc == 0) or not (0 <= r + dr < H and 0 <= c + dc < W):
                        continue
                    d = abs(z - e[r + dr, c + dc])
                    if d == d and not d <= st:  # fmax: NaN neither wins nor blocks
                        st = d
            bad = nan
            for v in (s / max_slope, st / max_step, rough[r, c] / max_rough):
                if v == v and not v <= bad:
                    bad = v
            if occ[r, c] >= occupied:
                t = 0.0
            elif bad == bad:
                t = min(max(1.0 - bad, 0.0), 1.0)
            else:
                t = nan
            slope[r, c] = s
            step[r, c] = st
            trav[r, c] = t

"""Numpy oracles of the compiled kernels of :mod:`sp.computation` (tests only).

:func:`ground_below_reference` is the oracle of :func:`sp.computation.ground_below` (each
pixel's ground height below it, carried from the nearest ground in front within the slope and
reach), :func:`segment_attributes_reference` of :func:`sp.computation.segment_attributes`
(every segment's sums, minima, maxima and box by ``np.bincount`` and sorting), and
:func:`ground_plane_reference` of :func:`sp.computation.ground_plane` (the least-squares plane
of the ground near a centre). The kernels must give the same results (see
``tests/test_kernel_equivalence.py``).
"""

from __future__ import annotations

import numpy as np

from sp.computation import ComputationError, SegmentAttributes


def ground_below_reference(
    ground: np.ndarray,
    z_world: np.ndarray,
    r_m: np.ndarray | None = None,
    max_slope: float = 0.3,
    max_reach_m: float = 15.0,
) -> np.ndarray:
    """:func:`ground_below` in plain numpy, one row of all columns at a time (the
    reference the compiled kernel is tested against)."""
    H, W = ground.shape
    out = np.full((H, W), np.nan)
    z1 = np.full(W, np.nan)
    r1 = np.zeros(W)
    slope = np.zeros(W)
    for i in range(H - 1, -1, -1):
        if r_m is None:
            out[i] = z1
        else:
            reach = np.clip(r_m[i] - r1, 0.0, max_reach_m)
            out[i] = z1 + slope * reach
        g = ground[i]
        if r_m is not None and g.any():
            dr = r_m[i] - r1
            fresh = g & np.isfinite(z1) & (dr > 0.5)
            s = np.clip((z_world[i] - z1) / np.where(fresh, dr, 1.0), -max_slope, max_slope)
            slope = np.where(fresh, s, slope)
            r1 = np.where(g, r_m[i], r1)
        z1 = np.where(g, z_world[i], z1)
    return out


def segment_attributes_reference(
    labels: np.ndarray,
    points_world: np.ndarray,
    intensity: np.ndarray,
    range_m: np.ndarray,
    t_offset_ns: np.ndarray,
    ground_z: np.ndarray,
    n_segments: int | None = None,
) -> SegmentAttributes:
    """:func:`segment_attributes` in plain numpy (``bincount`` / ``reduceat`` over the
    pixels sorted by label): the definition the compiled form is tested against. Same
    arguments and result.
    """
    if points_world.shape[:2] != labels.shape:
        raise ComputationError(f"points {points_world.shape} do not match labels {labels.shape}")
    lab = labels.reshape(-1)
    sel = np.flatnonzero(lab >= 0)
    K = int(lab[sel].max(initial=-1)) + 1 if n_segments is None else n_segments
    order = sel[np.argsort(lab[sel], kind="stable")]
    seg = lab[order]
    n = np.bincount(seg, minlength=K).astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(n)[:-1]])
    nz = n > 0
    n_safe = np.maximum(n, 1)
    p = points_world.reshape(-1, 3)[order].astype(np.float64)

    def mean(v: np.ndarray) -> np.ndarray:
        return np.bincount(seg, weights=v, minlength=K) / n_safe

    c = np.stack([mean(p[:, k]) for k in range(3)], axis=1)
    d = p - c[seg]
    cov = np.empty((K, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = mean(d[:, a] * d[:, b])
    evals, evecs = np.linalg.eigh(cov + 1e-9 * np.eye(3))
    curvature = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-12)
    verticality = np.abs(evecs[:, 2, 0])
    yaw = 0.5 * np.arctan2(2 * cov[:, 0, 1], cov[:, 0, 0] - cov[:, 1, 1])
    u = d[:, 0] * np.cos(yaw)[seg] + d[:, 1] * np.sin(yaw)[seg]
    v = -d[:, 0] * np.sin(yaw)[seg] + d[:, 1] * np.cos(yaw)[seg]

    def reduce(f: np.ufunc, x: np.ndarray, empty: float) -> np.ndarray:
        out = np.full(K, empty)
        if order.size:
            out[nz] = f.reduceat(x, starts[nz])
        return out

    u0, u1 = reduce(np.minimum, u, 0.0), reduce(np.maximum, u, 0.0)
    v0, v1 = reduce(np.minimum, v, 0.0), reduce(np.maximum, v, 0.0)
    z0, z1 = reduce(np.minimum, p[:, 2], 0.0), reduce(np.maximum, p[:, 2], 0.0)
    g = ground_z.reshape(-1)[order]
    has_g = np.isfinite(g)
    g_n = np.bincount(seg[has_g], minlength=K)
    g_mean = np.bincount(seg[has_g], weights=g[has_g], minlength=K) / np.maximum(g_n, 1)
    gz = np.where(g_n > 0, np.minimum(g_mean, z0), z0)
    length, width = u1 - u0, v1 - v0
    height = z1 - gz
    uc, vc = (u0 + u1) / 2, (v0 + v1) / 2
    center = np.stack(
        [
            c[:, 0] + uc * np.cos(yaw) - vc * np.sin(yaw),
            c[:, 1] + uc * np.sin(yaw) + vc * np.cos(yaw),
            gz + height / 2,
        ],
        axis=1,
    )
    inten = np.nan_to_num(intensity.reshape(-1)[order].astype(np.float64))
    t_off = t_offset_ns.reshape(-1)[order].astype(np.float64)
    range_ordered_m = range_m.reshape(-1)[order].astype(np.float64)
    return SegmentAttributes(
        n_pixels=n,
        centroid_xyz=c,
        center_xyz=center,
        yaw_rad=yaw,
        length_m=length,
        width_m=width,
        height_m=height,
        ground_z_m=gz,
        clearance_m=z0 - gz,
        area_m2=length * width,
        volume_m3=length * width * height,
        intensity=mean(inten),
        curvature=curvature,
        verticality=verticality,
        thickness_m=np.sqrt(np.maximum(evals[:, 0], 0.0)),
        breadth_m=np.sqrt(np.maximum(evals[:, 1], 0.0)),
        range_m=reduce(np.minimum, range_ordered_m, np.inf),
        t_offset_ns=np.round(mean(t_off)).astype(np.int64),
    )


def ground_plane_reference(
    xyz_w: np.ndarray, ground: np.ndarray, centre_xyz: np.ndarray, radius_m: float
) -> tuple[np.ndarray, float, int] | None:
    """The numpy form of :func:`ground_plane` (residuals taken point by point)."""
    d = xyz_w[ground] - np.asarray(centre_xyz, dtype=np.float64)
    near = d[d[:, 0] ** 2 + d[:, 1] ** 2 < radius_m**2]
    if near.shape[0] < 10:
        return None
    m = near.T @ near
    s = near.sum(axis=0)
    AtA = np.array([[m[0, 0], m[0, 1], s[0]], [m[0, 1], m[1, 1], s[1]], [s[0], s[1], len(near)]])
    coef, *_ = np.linalg.lstsq(AtA, np.array([m[0, 2], m[1, 2], s[2]]), rcond=None)
    resid = near[:, 2] - (coef[0] * near[:, 0] + coef[1] * near[:, 1] + coef[2])
    return coef, float(np.sqrt(np.mean(resid**2))), int(near.shape[0])

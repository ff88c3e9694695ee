"""Level 3 of SP beyond the ground: free-standing surfaces grouped from level-2 patches.

Reference 001, 4.5.6 "Level 3 Grouping": "surface patches in the same class that are
contiguous at their edges and have similar range, velocity, average surface orientation ...
may be grouped into surface entities"; "Level 3 Computation": area, position of the centre of
gravity, range, orientation, texture; "Level 3 Classification": generic surface classes (the
ground, sides of buildings, fences ...).

Grouping (:func:`group_patches`): two neighbouring patches of the grid (4-neighbours, columns
wrapping round the egosphere) join when their normals differ by less than ``max_angle_deg``
and each centroid lies within ``max_offset_m`` of the other's plane (coplanar and contiguous);
connected components of at least ``min_patches`` patches are surface hypotheses.

Tracking (:class:`SurfaceTracker`): a hypothesis continues the tracked surface whose normal
is within ``max_angle_deg`` and whose plane and centroid are close (``max_offset_m`` across the
plane, ``match_radius_m`` plus half its extent along it), largest first; otherwise it starts a
new one. A surface unseen for ``forget_s`` is dropped, so the table (and its KD frames) stay
bounded by what the sensor saw recently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from sp.lists import PatchGrid


class SurfaceError(ValueError):
    """A patch grid or surface table that does not fit; names it."""


@dataclass(frozen=True)
class SurfaceConfig:
    max_angle_deg: float = 15.0  # normals of joined patches / matched surfaces within this
    max_offset_m: float = 0.3  # centroid off the other plane by less than this
    min_patches: int = 3  # smaller components are no surface
    match_radius_m: float = 3.0  # centroid shift allowed along the plane (plus half its size)
    forget_s: float = 2.0  # a surface unseen this long is dropped
    confirm_hits: int = 3  # seen this many sweeps: confirmed


@dataclass
class SurfaceObservations:
    """S surface hypotheses of one sweep (gravity-aligned sensor frame, metres).

    label:       (B,) int64 surface index of every block of the grid, -1 none.
    n_pixels:    (S,) int64.
    area_m2:     (S,) float64 sum of the patches' pixel footprints.
    centroid:    (S, 3) float64 pixel-weighted mean point.
    normal:      (S, 3) float64 unit normal (pixel-weighted mean of the patch normals).
    roughness_m: (S,) float64 pixel-weighted mean patch roughness.
    height_m:    (S,) float64 highest minus lowest point.
    extent_m:    (S,) float64 largest horizontal distance of a patch centroid from the
                 surface's centroid.
    """

    label: np.ndarray
    n_pixels: np.ndarray
    area_m2: np.ndarray
    centroid: np.ndarray
    normal: np.ndarray
    roughness_m: np.ndarray
    height_m: np.ndarray
    extent_m: np.ndarray

    def __len__(self) -> int:
        return int(self.n_pixels.size)

    @property
    def slope_rad(self) -> np.ndarray:
        """(S,) angle of the surface to the horizontal (0 flat, pi/2 a wall)."""
        return np.arccos(np.clip(np.abs(self.normal[:, 2]), 0.0, 1.0))

    @property
    def azimuth_rad(self) -> np.ndarray:
        """(S,) direction the surface faces in the horizontal plane (atan2 of the normal)."""
        return np.arctan2(self.normal[:, 1], self.normal[:, 0])


@numba.njit(cache=True, nogil=True)
def _components_kernel(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    parent = np.arange(n)
    for k in range(a.size):
        x, y = a[k], b[k]
        while parent[x] != x:  # find with path halving
            parent[x] = parent[parent[x]]
            x = parent[x]
        while parent[y] != y:
            parent[y] = parent[parent[y]]
            y = parent[y]
        if x != y:
            parent[max(x, y)] = min(x, y)
    label = np.empty(n, dtype=np.int64)
    for k in range(n):  # roots have the smallest index of their component: seen first
        r = k
        while parent[r] != r:
            r = parent[r]
        label[k] = k if r == k else label[r]
    return label


def components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) int64 connected-component label of each of ``n`` nodes joined by the edges
    (a[k], b[k]): the smallest node index of its component. A compiled union-find (the scipy
    graph routine's set-up alone costs more than the whole search on these small graphs);
    :func:`components_scipy` is its reference."""
    a = np.ascontiguousarray(a, dtype=np.int64)
    b = np.ascontiguousarray(b, dtype=np.int64)
    if a.shape != b.shape or (a.size and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= n)):
        raise SurfaceError(f"edges {a.shape} / {b.shape} out of range for {n} nodes")
    return _components_kernel(n, a, b)


def components_scipy(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Reference of :func:`components` (scipy.sparse.csgraph), same labels."""
    m = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n, n))
    _, comp = connected_components(m, directed=False)
    first = np.full(comp.max(initial=-1) + 1, n, dtype=np.int64)
    np.minimum.at(first, comp, np.arange(n))
    return first[comp]


def _links(g: PatchGrid, cfg: SurfaceConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (a, b) of neighbouring patches that are coplanar."""
    nbr, nbc = g.shape
    idx = np.arange(nbr * nbc).reshape(nbr, nbc)
    a = np.concatenate([idx[:, :].reshape(-1), idx[:-1, :].reshape(-1)])
    b = np.concatenate([np.roll(idx, -1, axis=1).reshape(-1), idx[1:, :].reshape(-1)])
    keep = g.ok[a] & g.ok[b]
    a, b = a[keep], b[keep]
    na, nb = g.normal[a], g.normal[b]
    cos = np.einsum("ij,ij->i", na, nb)
    d = g.centroid[b] - g.centroid[a]
    off = np.maximum(np.abs(np.einsum("ij,ij->i", na, d)), np.abs(np.einsum("ij,ij->i", nb, d)))
    ok = (cos >= math.cos(math.radians(cfg.max_angle_deg))) & (off <= cfg.max_offset_m)
    return a[ok], b[ok]


def group_patches(
    g: PatchGrid, az_step_rad: float, el_step_rad: float, config: SurfaceConfig | None = None
) -> SurfaceObservations:
    """Surface hypotheses from the patches of ``g`` (module docstring); the footprint of a
    pixel at range r is r^2 * az_step * el_step over the cosine of its incidence (capped)."""
    cfg = config or SurfaceConfig()
    B = g.n.size
    if int(np.count_nonzero(g.ok)) < cfg.min_patches:
        return _no_surfaces(B)
    a, b = _links(g, cfg)
    comp = components(B, a, b)
    size = np.bincount(comp[g.ok], minlength=B)
    keep = size >= cfg.min_patches
    new = np.full(B, -1, dtype=np.int64)
    new[keep] = np.arange(int(keep.sum()))
    label = np.where(g.ok, new[comp], -1)
    S = int(keep.sum())
    on = label >= 0
    lab, n = label[on], g.n[on].astype(np.float64)
    npx = np.bincount(lab, weights=n, minlength=S)

    def wmean(x: np.ndarray) -> np.ndarray:
        return np.bincount(lab, weights=x * n, minlength=S) / np.maximum(npx, 1.0)

    c = g.centroid[on]
    r = np.linalg.norm(c, axis=1)
    inc = np.abs(np.einsum("ij,ij->i", g.normal[on], c)) / np.maximum(r, 1e-9)
    area = np.bincount(
        lab, weights=n * r * r * az_step_rad * el_step_rad / np.maximum(inc, 0.2), minlength=S
    )
    centroid = np.stack([wmean(c[:, k]) for k in range(3)], axis=1)
    normal = np.stack([wmean(g.normal[on][:, k]) for k in range(3)], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    z_lo = np.full(S, np.inf)
    z_hi = np.full(S, -np.inf)
    np.minimum.at(z_lo, lab, g.z_min[on])
    np.maximum.at(z_hi, lab, g.z_max[on])
    ext = np.zeros(S)
    np.maximum.at(ext, lab, np.linalg.norm((c - centroid[lab])[:, :2], axis=1))
    return SurfaceObservations(
        label=label,
        n_pixels=npx.astype(np.int64),
        area_m2=area,
        centroid=centroid,
        normal=normal,
        roughness_m=wmean(g.roughness_m[on]),
        height_m=z_hi - z_lo,
        extent_m=ext,
    )


def _no_surfaces(B: int) -> SurfaceObservations:
    z = np.zeros(0)
    return SurfaceObservations(
        np.full(B, -1, np.int64), np.zeros(0, np.int64), z, np.zeros((0, 3)), np.zeros((0, 3)),
        z, z, z,
    )  # fmt: skip


@dataclass
class SurfaceTracker:
    """Tracked free surfaces (world frame): ids, unit normals (T, 3), centroids (T, 3), extent
    (T,), hits (T,), last seen (T,) int64 ns."""

    config: SurfaceConfig = field(default_factory=SurfaceConfig)
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    centroid: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    extent: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hits: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    last_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def match(self, normal_w: np.ndarray, centroid_w: np.ndarray, area: np.ndarray) -> np.ndarray:
        """(S,) index into the table of the surface each observation continues, -1 new; each
        tracked surface is taken at most once, the largest observations choosing first."""
        cfg = self.config
        S, T = normal_w.shape[0], self.ids.size
        out = np.full(S, -1, dtype=np.int64)
        if S == 0 or T == 0:
            return out
        cos = np.abs(normal_w @ self.normal.T)
        d = centroid_w[:, None, :] - self.centroid[None, :, :]
        across = np.abs(np.einsum("tk,stk->st", self.normal, d))
        along = np.linalg.norm(d - across[..., None] * self.normal[None], axis=2)
        ok = (
            (cos >= math.cos(math.radians(cfg.max_angle_deg)))
            & (across <= 2.0 * cfg.max_offset_m)
            & (along <= cfg.match_radius_m + 0.5 * self.extent[None, :])
        )
        cost = np.where(ok, along + across, np.inf)
        taken = np.zeros(T, dtype=bool)
        for s in np.argsort(-area):
            c = np.where(taken, np.inf, cost[s])
            k = int(np.argmin(c))
            if np.isfinite(c[k]):
                out[s] = k
                taken[k] = True
        return out

    def update(
        self,
        index: np.ndarray,
        new_ids: np.ndarray,
        normal_w: np.ndarray,
        centroid_w: np.ndarray,
        extent: np.ndarray,
        t_ns: int,
    ) -> np.ndarray:
        """Write this sweep's observations: those with ``index`` >= 0 update their surface,
        the others append with ``new_ids`` (one per -1, in order). Returns (S,) their ids."""
        upd = index >= 0
        k = index[upd]
        self.normal[k] = (
            normal_w[upd] * np.sign(np.einsum("ij,ij->i", normal_w[upd], self.normal[k]))[:, None]
        )
        self.centroid[k] = centroid_w[upd]
        self.extent[k] = np.maximum(self.extent[k], extent[upd])
        self.hits[k] += 1
        self.last_ns[k] = t_ns
        fresh = ~upd
        if new_ids.size != int(fresh.sum()):
            raise SurfaceError(f"{new_ids.size} new ids for {int(fresh.sum())} new surfaces")
        start = self.ids.size
        self.ids = np.r_[self.ids, new_ids.astype(np.int64)]
        self.normal = np.r_[self.normal, normal_w[fresh]]
        self.centroid = np.r_[self.centroid, centroid_w[fresh]]
        self.extent = np.r_[self.extent, extent[fresh]]
        self.hits = np.r_[self.hits, np.ones(new_ids.size, np.int64)]
        self.last_ns = np.r_[self.last_ns, np.full(new_ids.size, t_ns, np.int64)]
        out = np.empty(index.size, dtype=np.int64)
        out[upd] = self.ids[k]
        out[fresh] = self.ids[start:]
        return out

    def forget(self, t_ns: int) -> np.ndarray:
        """Drop the surfaces unseen for ``forget_s``; returns their ids."""
        old = (t_ns - self.last_ns) > self.config.forget_s * 1e9
        gone = self.ids[old]
        if gone.size:
            keep = ~old
            for name in ("ids", "normal", "centroid", "extent", "hits", "last_ns"):
                setattr(self, name, getattr(self, name)[keep])
        return gone

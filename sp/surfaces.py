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

Filtering (reference 001, 4.5.4 eq. 4.3 and 4.5.6 "Level 3 Filtering": "a recursive estimation
process compares observed surface entity attributes with predicted surface entity attributes
... A confidence level associated with each estimated entity confirms or rejects the surface
entity grouping hypothesis"): every tracked surface carries a Kalman filter in filterpy's
symbols, run for all surfaces at once as stacked arrays. The state x (7,) is the plane and the
"what" attributes, ``STATE``: the normal vector (3, world frame, unit when observed), the
offset d (m) of the plane along it from the surface's anchor (its first centroid, so the
offset's variance does not grow with the distance from the world origin), area (m^2),
height (m) and roughness (m). A surface is static: F = I with a little process noise Q per
second; every component is observed, H = I. R comes from the plane fit: the normal's error
lies in the tangent plane with variance 12 sigma^2 / (N L^2) (N pixels of residual sigma
spread over L = sqrt(area)), the offset's from sigma^2 / N plus the normal's error over the
lever arm to the anchor (correlated with the normal's), the attributes' grow with their size
(the visible part of a wall changes with the view). The plane part's normalised innovation
squared (NIS, 4 dof) against its chi-square gate scores each sighting, the confidence moves
towards the score (``alpha``) and decays on misses (``miss_decay``): above ``confirm`` (after
``confirm_hits`` sightings) the hypothesis is confirmed, below ``deny`` it is denied (a
confirmed surface only on a sighting: one that merely leaves the view is forgotten). The
covariance update is Joseph's form, symmetrised, so P stays symmetric positive definite for
degenerate fits (one pixel, zero area, no normal).

Creases (:func:`find_creases`, 4.5.6 "Level 3 Computation": boundary types include slope
boundaries): two surfaces whose blocks lie within ``crease_gap_blocks`` of each other and
whose normals differ by more than ``crease_angle_deg`` meet along the intersection line of
their planes; the pixels near both surfaces whose points lie within ``crease_tol_m`` (or
``crease_tol_px`` pixel footprints) of that line are their crease, a level-2 ``slope_edge``
list of both. Its two passes, :func:`near_blocks` and :func:`crease_pixels`, are compiled
(numba; on first call, cached on disk); their numpy forms are test oracles
(``tests/kernel_reference/surfaces_reference.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from core.errors import EngineError
from sp.lists import PatchGrid
from sp.tracking import TrackStatus

STATE = ("normal_x", "normal_y", "normal_z", "offset_m", "area_m2", "height_m", "roughness_m")
N_STATE = len(STATE)
N_PLANE = 4  # the plane part of the state: normal (3) and offset
GATE_CHI2_4DOF = 18.47  # 99.9 % of a chi-square with 4 degrees of freedom


class SurfaceError(EngineError, ValueError):
    """A patch grid or surface table that does not fit; names it."""


@dataclass(frozen=True)
class SurfaceConfig:
    max_angle_deg: float = 15.0  # normals of joined patches / matched surfaces within this
    max_offset_m: float = 0.3  # centroid off the other plane by less than this
    min_patches: int = 3  # smaller components are no surface
    match_radius_m: float = 3.0  # centroid shift allowed along the plane (plus half its size)
    forget_s: float = 2.0  # a surface unseen this long is dropped
    confirm_hits: int = 3  # seen at least this many sweeps to be confirmed
    # filter (units per second of process noise, standard deviations)
    q_normal_per_s: float = 0.01  # random walk of the normal vector
    q_offset_m_per_s: float = 0.02
    q_area_m2_per_s: float = 2.0
    q_height_m_per_s: float = 0.2
    q_roughness_m_per_s: float = 0.01
    sigma_fit_m: float = 0.02  # floor of the fit's residual sigma (range noise)
    sigma_normal: float = 0.02  # floor of the normal's error (mean of patch normals)
    sigma_offset_m: float = 0.05  # floor of the offset's error
    area_rel: float = 0.25  # area sigma: area_rel * area + area_m2
    area_m2: float = 1.0
    height_rel: float = 0.2
    height_m: float = 0.2
    roughness_rel: float = 0.5
    roughness_m: float = 0.02
    # confirm / deny (as sp.tracking: confidence moves towards exp(-max(NIS - 4, 0) / 8))
    gate_chi2: float = GATE_CHI2_4DOF
    confidence0: float = 0.3
    alpha: float = 0.6
    miss_decay: float = 0.2
    confirm: float = 0.6
    deny: float = 0.15
    # creases between surfaces
    crease_angle_deg: float = 30.0  # normals differ by more than this
    crease_gap_blocks: int = 2  # surfaces' blocks this close (grid steps) may meet
    crease_tol_m: float = 0.1  # crease pixels lie this close to the planes' intersection,
    crease_tol_px: float = 1.5  # or this many pixel footprints (range x azimuth step)


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

    def take(self, keep: np.ndarray) -> SurfaceObservations:
        """The surfaces ``keep`` ((S,) bool) of these, renumbered in order (blocks of the
        others unlabelled)."""
        new = np.full(len(self) + 1, -1, dtype=np.int64)  # last: label -1 stays -1
        new[:-1][keep] = np.arange(int(np.count_nonzero(keep)))
        return SurfaceObservations(
            new[self.label], self.n_pixels[keep], self.area_m2[keep], self.centroid[keep],
            self.normal[keep], self.roughness_m[keep], self.height_m[keep], self.extent_m[keep],
        )  # fmt: skip

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


# ---------------------------------------------------------------- recursive estimation


def process_noise(dt_s: np.ndarray, config: SurfaceConfig) -> np.ndarray:
    """(T, 7, 7) Q of the static-surface model over intervals dt_s (T,) seconds (a random
    walk: variance per second times the interval)."""
    c = config
    q = np.array(
        [c.q_normal_per_s] * 3
        + [c.q_offset_m_per_s, c.q_area_m2_per_s, c.q_height_m_per_s, c.q_roughness_m_per_s]
    )
    Q = np.zeros((dt_s.size, N_STATE, N_STATE))
    idx = np.arange(N_STATE)
    Q[:, idx, idx] = q * q * np.maximum(dt_s, 0.0)[:, None]
    return Q


def measure(
    obs: SurfaceObservations,
    centroid_w: np.ndarray,
    anchor_w: np.ndarray,
    normal_ref: np.ndarray,
    config: SurfaceConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Measurement z (S, 7) and its noise R (S, 7, 7) of S observed surfaces (module
    docstring). ``centroid_w`` (S, 3) world centroids, ``anchor_w`` (S, 3) the anchors of
    the surfaces they update (the centroid itself for a new one), ``normal_ref`` (S, 3) the
    estimated normals they update: the observed normal is flipped to agree (a plane has two).
    A degenerate fit (zero normal, one pixel, zero area) gets a large, still positive
    definite R."""
    c = config
    S = len(obs)
    n = obs.normal.astype(np.float64)
    norm = np.linalg.norm(n, axis=1)
    flat = norm < 0.5  # no normal from the fit
    n = n / np.maximum(norm, 1e-12)[:, None]
    n *= np.where(np.einsum("ij,ij->i", n, normal_ref) < 0.0, -1.0, 1.0)[:, None]
    r = centroid_w - anchor_w  # lever arm to the anchor (m)
    sigma = np.maximum(np.nan_to_num(obs.roughness_m), c.sigma_fit_m)
    N = np.maximum(obs.n_pixels, 1).astype(np.float64)
    L2 = np.maximum(np.nan_to_num(obs.area_m2), 0.01)
    var_n = np.minimum(12.0 * sigma**2 / (N * L2), 1.0) + c.sigma_normal**2
    nn = np.einsum("si,sj->sij", n, n)
    R_nn = var_n[:, None, None] * (np.eye(3) - nn) + c.sigma_normal**2 * nn
    R_nn[flat] = np.eye(3)
    z = np.zeros((S, N_STATE))
    z[:, :3] = np.where(flat[:, None], normal_ref, n)
    z[:, 3] = np.einsum("ij,ij->i", z[:, :3], r)
    z[:, 4], z[:, 5], z[:, 6] = obs.area_m2, obs.height_m, obs.roughness_m
    R = np.zeros((S, N_STATE, N_STATE))
    R[:, :3, :3] = R_nn
    cross = np.einsum("sij,sj->si", R_nn, r)  # cov(normal, offset) through the lever arm
    R[:, :3, 3] = R[:, 3, :3] = cross
    R[:, 3, 3] = sigma**2 / N + c.sigma_offset_m**2 + np.einsum("si,si->s", r, cross)
    R[:, 4, 4] = (c.area_rel * np.abs(z[:, 4]) + c.area_m2) ** 2
    R[:, 5, 5] = (c.height_rel * np.abs(z[:, 5]) + c.height_m) ** 2
    R[:, 6, 6] = (c.roughness_rel * np.abs(z[:, 6]) + c.roughness_m) ** 2
    return np.nan_to_num(z), R


def predict(x: np.ndarray, P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x*(t|t-1) = F x, P* = F P F' + Q with F = I (a static surface): (x, P + Q)."""
    return x, P + Q


def update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x(t|t) = x* + K (z - H x*) with H = I, for stacked filters x (T, 7), P (T, 7, 7),
    z (T, 7), R (T, 7, 7). Returns (x, P, NIS of the plane part (T,)); Joseph-form
    covariance, symmetrised."""
    y = z - x  # innovation y(t) - y*(t|t-1)
    S = P + R
    K = np.linalg.solve(S, P).transpose(0, 2, 1)  # P S^-1 (P and S symmetric)
    x_new = x + np.einsum("tij,tj->ti", K, y)
    IKH = np.eye(N_STATE) - K
    P_new = IKH @ P @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
    P_new = 0.5 * (P_new + P_new.transpose(0, 2, 1))
    yp = y[:, :N_PLANE]
    w = np.linalg.solve(S[:, :N_PLANE, :N_PLANE], yp[..., None])[..., 0]
    nis = np.einsum("ti,ti->t", yp, w)
    return x_new, P_new, nis


def sighting_score(nis: np.ndarray, gate_chi2: float) -> np.ndarray:
    """(T,) how well a sighting fits its prediction: exp(-max(NIS - 4, 0) / 8) inside the
    chi-square gate (4 dof, mean 4), 0 outside."""
    return np.where(nis <= gate_chi2, np.exp(-np.maximum(nis - N_PLANE, 0.0) / (2 * N_PLANE)), 0.0)


_TABLE = ("ids", "normal", "centroid", "extent", "hits", "last_ns", "x", "P", "anchor",
          "status", "confidence", "nis")  # fmt: skip


@dataclass
class SurfaceTracker:
    """Tracked free surfaces (world frame), T rows: ids, unit normals (T, 3) (the filter's),
    last observed centroids (T, 3), extent (T,), hits (T,), last seen (T,) int64 ns; the
    filters x (T, 7), P (T, 7, 7) (``STATE``), anchors (T, 3); status (T,) int8
    (:class:`sp.tracking.TrackStatus`), confidence (T,), the last sighting's NIS (T,)."""

    config: SurfaceConfig = field(default_factory=SurfaceConfig)
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    centroid: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    extent: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hits: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    last_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    x: np.ndarray = field(default_factory=lambda: np.zeros((0, N_STATE)))
    P: np.ndarray = field(default_factory=lambda: np.zeros((0, N_STATE, N_STATE)))
    anchor: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    status: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    nis: np.ndarray = field(default_factory=lambda: np.zeros(0))

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
        obs: SurfaceObservations,
        centroid_w: np.ndarray,
        t_ns: int,
    ) -> np.ndarray:
        """One sweep's filtering: observations with ``index`` >= 0 update their surface's
        filter (predict over the time since its last sighting, update, score the NIS), the
        others are born with ``new_ids`` (one per -1, in order; x = z, P = R); the surfaces
        not seen decay. Then each hypothesis is confirmed or denied. Returns (S,) the ids of
        the observations (look their rows up by :meth:`rows`)."""
        cfg = self.config
        upd = index >= 0
        fresh = ~upd
        if new_ids.size != int(fresh.sum()):
            raise SurfaceError(f"{new_ids.size} new ids for {int(fresh.sum())} new surfaces")
        k = index[upd]
        seen = np.zeros(self.ids.size, dtype=bool)
        seen[k] = True
        if k.size:
            z, R = measure(obs.take(upd), centroid_w[upd], self.anchor[k], self.normal[k], cfg)
            dt = (t_ns - self.last_ns[k]) * 1e-9
            x, P = predict(self.x[k], self.P[k], process_noise(dt, cfg))
            self.x[k], self.P[k], self.nis[k] = update(x, P, z, R)
            score = sighting_score(self.nis[k], cfg.gate_chi2)
            self.confidence[k] += cfg.alpha * (score - self.confidence[k])
            est = self.x[k, :3]
            self.normal[k] = est / np.maximum(np.linalg.norm(est, axis=1), 1e-12)[:, None]
            self.centroid[k] = centroid_w[upd]
            self.extent[k] = np.maximum(self.extent[k], obs.extent_m[upd])
            self.hits[k] += 1
            self.last_ns[k] = t_ns
        self.confidence[~seen] *= 1.0 - cfg.miss_decay
        self._confirm_or_deny(seen)
        start = self.ids.size
        if new_ids.size:
            c_new = centroid_w[fresh]
            born = obs.take(fresh)
            z, R = measure(born, c_new, c_new, born.normal, cfg)
            n = new_ids.size
            self._append(
                ids=new_ids.astype(np.int64),
                normal=z[:, :3].copy(),
                centroid=c_new,
                extent=born.extent_m,
                hits=np.ones(n, np.int64),
                last_ns=np.full(n, t_ns, np.int64),
                x=z,
                P=R,
                anchor=c_new,
                status=np.full(n, TrackStatus.HYPOTHESIZED, np.int8),
                confidence=np.full(n, cfg.confidence0),
                nis=np.zeros(n),
            )
        out = np.empty(index.size, dtype=np.int64)
        out[upd] = self.ids[k]
        out[fresh] = self.ids[start:]
        return out

    def _confirm_or_deny(self, seen: np.ndarray) -> None:
        cfg = self.config
        hyp = self.status == TrackStatus.HYPOTHESIZED
        conf = self.status == TrackStatus.CONFIRMED
        low = self.confidence < cfg.deny
        up = hyp & (self.confidence >= cfg.confirm) & (self.hits >= cfg.confirm_hits)
        self.status[up] = TrackStatus.CONFIRMED
        self.status[(hyp & low) | (conf & seen & low)] = TrackStatus.DENIED

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """(n,) table rows of surface ``ids`` (each must be in the table)."""
        order = np.argsort(self.ids)
        pos = order[np.searchsorted(self.ids, ids, sorter=order)]
        if ids.size and not np.array_equal(self.ids[pos], ids):
            raise SurfaceError(f"surface ids {ids[self.ids[pos] != ids]} not in the table")
        return pos

    def plane(self) -> tuple[np.ndarray, np.ndarray]:
        """The estimated planes: unit normals (T, 3) and offsets (T,) m, world frame, so that
        a point p on surface t has normal[t] . p = offset[t]."""
        return self.normal, self.x[:, 3] / np.maximum(
            np.linalg.norm(self.x[:, :3], axis=1), 1e-12
        ) + np.einsum("ij,ij->i", self.normal, self.anchor)

    def drop_denied(self) -> np.ndarray:
        """Remove the denied surfaces; returns their ids."""
        out = self.ids[self.status == TrackStatus.DENIED]
        if out.size:
            self._keep(self.status != TrackStatus.DENIED)
        return out

    def forget(self, t_ns: int) -> np.ndarray:
        """Drop the surfaces unseen for ``forget_s``; returns their ids."""
        old = (t_ns - self.last_ns) > self.config.forget_s * 1e9
        gone = self.ids[old]
        if gone.size:
            self._keep(~old)
        return gone

    def _keep(self, keep: np.ndarray) -> None:
        for name in _TABLE:
            setattr(self, name, getattr(self, name)[keep])

    def _append(self, **rows: np.ndarray) -> None:
        for name in _TABLE:
            setattr(self, name, np.concatenate([getattr(self, name), rows[name]]))


# ---------------------------------------------------------------- creases


@dataclass
class Creases:
    """C creases (slope boundaries) between pairs of surfaces.

    a, b:   (C,) int64 indices of the two surfaces (a < b) in the labels given.
    pixel:  (K,) int64 flat pixel indices (row * W + col) of the creases' pixels.
    crease: (K,) int64 the crease of each pixel (index into a, b).
    """

    a: np.ndarray
    b: np.ndarray
    pixel: np.ndarray
    crease: np.ndarray

    def __len__(self) -> int:
        return int(self.a.size)


def _no_creases() -> Creases:
    z = np.zeros(0, np.int64)
    return Creases(z, z, z, z)


def plane_fit(
    label: np.ndarray, xyz: np.ndarray, n_labels: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares planes of labelled pixels: ``label`` (N,) int64 in [0, n_labels), ``xyz``
    (N, 3) float64 points (m). Returns (centroid (L, 3), unit normal (L, 3) the smallest
    scatter axis, zero for a label without pixels, pixels (L,) int64)."""
    n = np.bincount(label, minlength=n_labels).astype(np.float64)
    k = np.maximum(n, 1.0)[:, None]
    mean = np.stack([np.bincount(label, xyz[:, i], n_labels) for i in range(3)], axis=1) / k
    d = xyz - mean[label]
    cov = np.einsum("ni,nj->nij", d, d).reshape(-1, 9)
    cov = np.stack([np.bincount(label, cov[:, i], n_labels) for i in range(9)], axis=1)
    _, v = np.linalg.eigh(cov.reshape(-1, 3, 3))
    normal = np.where(n[:, None] > 0, v[:, :, 0], 0.0)
    return mean, normal, n.astype(np.int64)


@numba.njit(cache=True, nogil=True)
def _near_blocks_kernel(block_label: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray]:
    nbr, nbc = block_label.shape
    cap = nbr * nbc * (gap + 1) * (2 * gap + 1)
    out_i = np.empty(cap, np.int64)
    out_j = np.empty(cap, np.int64)
    n = 0
    for r in range(nbr):
        for c in range(nbc):
            la = block_label[r, c]
            if la < 0:
                continue
            for dr in range(min(gap, nbr - 1 - r) + 1):
                for dc in range(-gap, gap + 1):
                    if (dr == 0 and dc <= 0) or 2 * abs(dc) > nbc:
                        continue
                    c2 = (c + dc) % nbc
                    lb = block_label[r + dr, c2]
                    if lb >= 0 and lb != la:
                        out_i[n] = r * nbc + c
                        out_j[n] = (r + dr) * nbc + c2
                        n += 1
    return out_i[:n], out_j[:n]


def near_blocks(block_label: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of blocks (i, j) (flat indices into the (nbr, nbc) grid ``block_label``) of
    different surfaces (labels >= 0) within ``gap`` grid steps (Chebyshev distance, columns
    wrapping round), each pair once. One compiled pass over the grid;
    ``near_blocks_reference`` (a test oracle) is its numpy form (same pairs, another order)."""
    return _near_blocks_kernel(np.ascontiguousarray(block_label, dtype=np.int64), int(gap))


@numba.njit(cache=True, nogil=True)
def _crease_pixels_kernel(
    pair: np.ndarray,
    blk: np.ndarray,
    nbc: int,
    bh: int,
    bw: int,
    label: np.ndarray,
    free: np.ndarray,
    xyz: np.ndarray,
    id_a: np.ndarray,
    id_b: np.ndarray,
    p0: np.ndarray,
    u: np.ndarray,
    tol2: float,
    per2: float,
) -> tuple[np.ndarray, np.ndarray]:
    H, W = label.shape
    out_px = np.empty(pair.size * bh * bw, np.int64)
    out_q = np.empty(pair.size * bh * bw, np.int64)
    n = 0
    for k in range(pair.size):
        q = pair[k]
        r0 = (blk[k] // nbc) * bh
        c0 = (blk[k] % nbc) * bw
        for r in range(r0, min(r0 + bh, H)):
            for c in range(c0, min(c0 + bw, W)):
                own = label[r, c]
                if not (own == id_a[q] or own == id_b[q] or (own < 0 and free[r, c])):
                    continue
                dx = xyz[r, c, 0] - p0[q, 0]
                dy = xyz[r, c, 1] - p0[q, 1]
                dz = xyz[r, c, 2] - p0[q, 2]
                along = dx * u[q, 0] + dy * u[q, 1] + dz * u[q, 2]
                range_sq_m2 = xyz[r, c, 0] ** 2 + xyz[r, c, 1] ** 2 + xyz[r, c, 2] ** 2
                if dx * dx + dy * dy + dz * dz - along * along <= max(tol2, per2 * range_sq_m2):
                    out_px[n] = r * W + c
                    out_q[n] = q
                    n += 1
    return out_px[:n], out_q[:n]


def crease_pixels(
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
    """The pixels of candidate crease ``pair[k]`` in block ``blk[k]`` (flat index into a grid
    of ``n_block_cols`` columns of ``block`` (rows, cols) pixels) that belong to either of its
    surfaces (``label`` (H, W) int64 equal to ``id_a`` or ``id_b`` (C,) of the pair) or to
    none while ``free`` (H, W) bool, and whose point ``xyz`` (H, W, 3) lies within ``tol_m``
    of the pair's line (through ``p0`` (C, 3), unit direction ``u`` (C, 3)), or within
    ``tol_per_m`` times its range from the origin if that is more. Returns (flat
    pixel (K,) int64, pair (K,) int64), in the order of the blocks given, row-major inside
    each. One compiled pass; ``crease_pixels_reference`` (a test oracle) is its numpy form
    (same output)."""
    return _crease_pixels_kernel(
        np.ascontiguousarray(pair, dtype=np.int64),
        np.ascontiguousarray(blk, dtype=np.int64),
        int(n_block_cols),
        int(block[0]),
        int(block[1]),
        np.ascontiguousarray(label, dtype=np.int64),
        np.ascontiguousarray(free, dtype=np.bool_),
        np.ascontiguousarray(xyz, dtype=np.float64),
        np.ascontiguousarray(id_a, dtype=np.int64),
        np.ascontiguousarray(id_b, dtype=np.int64),
        np.ascontiguousarray(p0, dtype=np.float64),
        np.ascontiguousarray(u, dtype=np.float64),
        float(tol_m) ** 2,
        float(tol_per_m) ** 2,
    )


def find_creases(
    block_label: np.ndarray,
    block: tuple[int, int],
    label: np.ndarray,
    free: np.ndarray,
    xyz: np.ndarray,
    ids: np.ndarray,
    normal: np.ndarray,
    point: np.ndarray,
    config: SurfaceConfig | None = None,
    az_step_rad: float = 0.0,
) -> Creases:
    """Creases between surfaces (module docstring), all pairs at once.

    block_label: (nbr, nbc) int64 surface index of each block of the patch grid, -1 none.
    block:       (rows, cols) pixels per block.
    label:       (H, W) int64 label of each pixel (an entity id, say), -1 none.
    free:        (H, W) bool unlabelled pixels that may lie on a crease.
    xyz:         (H, W, 3) points (m), in the frame of the planes (NaN where none).
    ids:         (S,) int64 the label of each surface's pixels.
    normal, point: (S, 3) unit normal and a point of each surface's plane.
    az_step_rad: azimuth step of the image: the tolerance is at least ``crease_tol_px``
                 pixel footprints at the pixel's range (points in a sensor-centred frame).

    A crease's pixels lie in the blocks spanned by two close blocks of its surfaces (the
    blocks themselves and any gap between them), belong to either surface (or to none, when
    free), and lie within ``crease_tol_m`` of the line where the two planes meet.
    """
    cfg = config or SurfaceConfig()
    nbr, nbc = block_label.shape
    g = cfg.crease_gap_blocks
    i, j = near_blocks(block_label, g)
    if i.size == 0:
        return _no_creases()
    flat = block_label.reshape(-1)
    la, lb = flat[i], flat[j]
    la, lb = np.minimum(la, lb), np.maximum(la, lb)
    S = normal.shape[0]
    key, inv = np.unique(la * S + lb, return_inverse=True)
    a, b = np.divmod(key, S)
    cos = np.abs(np.einsum("ij,ij->i", normal[a], normal[b]))
    sharp = cos < math.cos(math.radians(cfg.crease_angle_deg))
    if not sharp.any():
        return _no_creases()
    a, b = a[sharp], b[sharp]
    keep = sharp[inv]
    i, j, pair = i[keep], j[keep], (np.cumsum(sharp) - 1)[inv[keep]]
    # the blocks spanned by each close block pair: its corner nearest the origin and its size
    ri, ci = np.divmod(i, nbc)
    rj, cj = np.divmod(j, nbc)
    dc = (cj - ci + nbc // 2) % nbc - nbc // 2  # signed, round the wrap
    r0, c0 = np.minimum(ri, rj), ci + np.minimum(dc, 0)
    off_r, off_c = np.divmod(np.arange((g + 1) * (g + 1)), g + 1)
    inside = (off_r <= np.abs(rj - ri)[:, None]) & (off_c <= np.abs(dc)[:, None])
    k, o = np.nonzero(inside)
    pb = np.unique(pair[k] * (nbr * nbc) + (r0[k] + off_r[o]) * nbc + (c0[k] + off_c[o]) % nbc)
    pair_blk, blk = np.divmod(pb, nbr * nbc)
    # the line where the two planes meet: direction u, through p0
    na, nb = normal[a], normal[b]
    u = np.cross(na, nb)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rhs = np.stack([np.einsum("ij,ij->i", na, point[a]), np.einsum("ij,ij->i", nb, point[b])])
    p0 = np.linalg.solve(np.stack([na, nb, u], axis=1), np.r_[rhs, [0.0 * a]].T[..., None])
    args = (pair_blk, blk, nbc, block, label, free, xyz, ids[a], ids[b], p0[..., 0], u)
    tol = (cfg.crease_tol_m, cfg.crease_tol_px * az_step_rad)
    px, q = crease_pixels(*args, *tol)
    used, crease = np.unique(q, return_inverse=True)
    return Creases(a[used], b[used], px, crease.astype(np.int64))

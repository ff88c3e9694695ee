"""SP level 3: surfaces (the ground, objects' faces, free-standing surfaces, their creases).

Reference 001, 4.5.6 (level 3: surfaces grouped from patches; their contact boundaries and
creases are level-2 lists), 4.5.1 (the five SP functions), 4.5.3 (hypothesize and test),
4.5.4 (recursive estimation). Per sweep:

- windowing: none;
- grouping: the ground (:meth:`SurfaceLevel.ground_pixels`), the vertical face of a confirmed
  object (:func:`vertical_face`), coplanar contiguous patches of the remaining pixels
  (:func:`patch_grid`, :func:`group_patches`);
- computation: slope, roughness, height, length, area, range, azimuth (:func:`ground_plane`);
- filtering: the ground and faces are made confirmed; free surfaces by
  :class:`SurfaceTracker` (Kalman filter of plane and attributes, confidence confirms or
  denies, unseen for ``forget_s`` is gone);
- classification: against the level-3 prototypes.

The surfaces' frames, states and relations are observations (:mod:`sp.observations`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from kd_store import Attribute, Level, Status
from sp.classify import Classifier
from sp.computation import SegmentAttributes, ground_plane
from sp.context import IMAGE_NAMES, KD_STATUS, SPConfig, SPContext, row_step, unit
from sp.ground import ground_mask, raised_in_rows
from sp.ground_prior import GROUND, OBJECT, GroundPrior, above_prior, on_known_ground
from sp.level2_lists import ListLevel
from sp.lists import PatchGrid, patch_grid
from sp.observations import FrameChange, Related, StateObserved, StateRule
from sp.surfaces import (
    SurfaceObservations,
    SurfaceTracker,
    find_creases,
    group_patches,
    plane_fit,
)
from sp.tracking import TrackStatus


@dataclass
class GroundPixels:
    """Level 3's ground of one sweep, (H, W) bool each.

    ground:    the ground pixels.
    standing:  returns found standing on the terrain, by their row
               (:func:`sp.ground.raised_in_rows`) or, far out, well above the ground the
               world model's ground prior expects (:func:`sp.ground_prior.above_prior`):
               their segment is an object however low it stands over its column's ground.
    on_known:  returns off the ground that lie on the ground the world model knows at their
               places (:func:`sp.ground_prior.on_known_ground`).
    """

    ground: np.ndarray
    standing: np.ndarray
    on_known: np.ndarray


@dataclass
class SurfacesObserved:
    """Level 3 of one sweep, on the egosphere grid (H, W).

    image:     (H, W) int64 surface entity id per pixel (ground, faces, free surfaces), -1.
    contact:   (H, W) int64 id of the level-2 contact boundary or crease on the pixel, -1.
    surfaces:  ids of the free-standing surfaces observed this sweep (not denied).
    free_px:   (H, W) bool pixels of the free surfaces (their level-2 surface patches).
    """

    image: np.ndarray
    contact: np.ndarray
    surfaces: list[int]
    free_px: np.ndarray


class SurfaceLevel:
    """Level-3 surface entities: one ground, a face per confirmed object that shows one, and
    the free-standing surfaces tracked from sweep to sweep; ``lists`` is level 2, whose lists
    of a surface go when the surface goes."""

    def __init__(self, ctx: SPContext, lists: ListLevel) -> None:
        self.ctx = ctx
        self.lists = lists
        self.ground_id: int | None = None
        self.track_surface: dict[int, tuple[int, int]] = {}  # object -> (face, contact) ids
        self.surface_tracker = SurfaceTracker(ctx.config.surfaces)
        self._surface_contact: dict[int, int] = {}  # free surface id -> its contact list id
        self._surface_status: dict[int, int] = {}  # free surface id -> status written to KD
        self._crease: dict[tuple[int, int], tuple[int, int]] = {}  # surfaces -> (list, t_ns)
        self.classifier = Classifier(ctx.classes, Level.SURFACE, ctx.config.classify)

    # ------------------------------------------------------------------ grouping: the ground

    def ground_pixels(
        self,
        xyz_g: np.ndarray,
        valid: np.ndarray,
        xyz_w: np.ndarray | None = None,
        range_m: np.ndarray | None = None,
        prior: GroundPrior | None = None,
    ) -> GroundPixels:
        """The ground of the gravity-aligned points ``xyz_g`` (H, W, 3) m
        (:func:`ground_mask`), less the returns their row shows standing on it
        (:func:`raised_in_rows`, which make their segment an object however low it stands
        over its column's ground). With the world model's ground ``prior``, the world points
        ``xyz_w`` (H, W, 3) m and the returns' ranges ``range_m`` (H, W) m, far returns well
        above the ground it expects are not ground, those higher still make their segment
        an object (:func:`above_prior`), and the other returns on the ground it knows are
        marked (:func:`on_known_ground`); without, none is."""
        cfg = self.ctx.config
        ground, _h = ground_mask(xyz_g, valid, cfg.ground)
        raised = raised_in_rows(xyz_g, valid, ground, cfg.ground)
        ground &= ~raised
        if prior is None or xyz_w is None or range_m is None:
            return GroundPixels(ground, raised, np.zeros_like(ground))
        code = above_prior(xyz_w, range_m, ground, prior, cfg.ground_prior)
        ground &= code == GROUND
        # only returns off the ground can make segments, so only those are marked
        known = on_known_ground(xyz_w, range_m, valid & ~ground, prior, cfg.ground_prior)
        return GroundPixels(ground, (code == OBJECT) | raised, known)

    # ------------------------------------------------------------------ the cycle

    def step(
        self,
        t_ns: int,
        xyz_w: np.ndarray,
        xyz_g: np.ndarray,
        valid: np.ndarray,
        ground: np.ndarray,
        labels: np.ndarray,
        a: SegmentAttributes,
        obj_ids: np.ndarray,
        confirmed_ids: np.ndarray,
        in_object: np.ndarray,
        T_world_ladar: np.ndarray,
        row_el: np.ndarray,
    ) -> SurfacesObserved:
        """Level 3 of one sweep: the ground entity on the ``ground`` pixels (H, W) bool, the
        faces of the confirmed objects (``confirmed_ids``) among level 4's segments
        (``labels`` (H, W) segment per pixel, ``a`` their attributes, ``obj_ids`` (K,) their
        object ids), then the free surfaces on the valid pixels left: not ground, not in a
        confirmed object (``in_object`` (H, W) bool), not a face. ``xyz_w`` / ``xyz_g``
        (H, W, 3) are the points in the world and gravity-aligned sensor frames (m),
        ``row_el`` (H,) the rows' elevations (rad)."""
        H, W = valid.shape
        image = np.full((H, W), -1, dtype=np.int64)
        image[ground] = self.ground_entity(t_ns, xyz_w, ground, T_world_ladar)
        image, contact = self.faces(t_ns, image, labels, a, obj_ids, ground, confirmed_ids)
        surfaces: list[int] = []
        free_px = np.zeros((H, W), dtype=bool)  # pixels of free surfaces (patches)
        if self.ctx.config.free_surfaces:
            free = valid & ~ground & ~in_object & (image < 0)
            image, surfaces = self.free_surfaces(
                t_ns, image, contact, xyz_g, free, ground, T_world_ladar, row_el, free_px
            )
        return SurfacesObserved(image, contact, surfaces, free_px)

    # ------------------------------------------------------------------ the ground

    def ground_entity(
        self, t_ns: int, xyz_w: np.ndarray, ground: np.ndarray, T_world_ladar: np.ndarray
    ) -> int:
        """The ground's level-3 entity, its plane fitted to the ground pixels ``ground`` (H, W)
        of ``xyz_w`` (H, W, 3) world points within 20 m of the sensor (:func:`ground_plane`)."""
        ctx = self.ctx
        if self.ground_id is None:
            self.ground_id = ctx.new_entity(
                "ground",
                Level.SURFACE,
                generic_classes=("ground",) if "ground" in ctx.classes else (),
                images=(IMAGE_NAMES[3],),
                status=Status.CONFIRMED,
                confidence=1.0,
            )
            ctx.set_class(self.ground_id, "ground")
        gid = self.ground_id
        fit = ground_plane(xyz_w, ground, T_world_ladar[:3, 3], 20.0)
        if fit is not None:
            coef, rough, n_near = fit
            slope = float(math.atan(math.hypot(coef[0], coef[1])))
            z0 = float(T_world_ladar[2, 3] + coef[2])  # the plane under the sensor
            attributes = {
                "slope_rad": Attribute(observed=slope, observed_var=0.01),
                "roughness_m": Attribute(observed=rough, observed_var=0.0001),
                "n_pixels": Attribute(observed=float(n_near)),
            }
            ctx.record(FrameChange(gid, attributes=attributes))
            pos = np.array([T_world_ladar[0, 3], T_world_ladar[1, 3], z0])
            ctx.record(StateObserved(gid, t_ns, pos, np.zeros(3), StateRule.IF_NEWER))
        return gid

    # ------------------------------------------------------------------ objects' faces

    def faces(
        self,
        t_ns: int,
        image3: np.ndarray,
        labels: np.ndarray,
        a: SegmentAttributes,
        obj_ids: np.ndarray,
        ground: np.ndarray,
        confirmed_ids: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Level 3 beyond the ground: the vertical planar face of a confirmed object (a wall, a
        building side) is a surface entity, part of that object, classified among the level's
        prototypes (slope, roughness, height); where it meets the ground, the pixels of the
        face just above a ground pixel are its contact boundary (a level-2 list lying on the
        ground). Returns (image3 with the faces, (H, W) int64 contact-boundary ids, -1 none)."""
        confirmed = set(confirmed_ids.tolist())
        face_of = np.full(len(a) + 1, -1, dtype=np.int64)  # per segment (last: no segment)
        contact_of = face_of.copy()
        for s in np.flatnonzero(vertical_face(a, self.ctx.config)):
            oid = int(obj_ids[s])
            if oid not in confirmed:
                continue
            face_of[s], contact_of[s] = self._surface_of(oid, t_ns)
            attrs = {
                "slope_rad": math.acos(min(float(a.verticality[s]), 1.0)),
                "roughness_m": float(a.thickness_m[s]),
                "height_m": float(a.height_m[s]),
                "length_m": float(a.length_m[s]),
            }
            m = self.classifier.classify(attrs)
            self.ctx.record(
                FrameChange(
                    int(face_of[s]),
                    attributes={k: Attribute(observed=v) for k, v in attrs.items()},
                    generic_classes=m.generic,
                )
            )
            self.ctx.set_class(int(face_of[s]), m.name)
        face = face_of[labels]  # labels -1 picks the last entry: no face
        image3 = np.where(face >= 0, face, image3)
        above_ground = np.zeros_like(ground)
        above_ground[:-1] = ground[1:]
        contact = np.where((face >= 0) & above_ground, contact_of[labels], -1)
        return image3, contact

    def _surface_of(self, oid: int, t_ns: int) -> tuple[int, int]:
        """(surface id, contact boundary id) of object ``oid``'s face, made on first sight."""
        if oid not in self.track_surface:
            ctx = self.ctx
            sid = ctx.new_entity(
                f"face of {oid}",
                Level.SURFACE,
                images=(IMAGE_NAMES[3],),
                status=Status.CONFIRMED,
                confidence=1.0,
            )
            ctx.record(Related(sid, "belongs_to", oid, t_ns))
            bid = self._contact_list(sid, t_ns)
            self.track_surface[oid] = (sid, bid)
        return self.track_surface[oid]

    def _contact_list(self, sid: int, t_ns: int) -> int:
        """A new contact boundary of surface ``sid`` with the ground: a confirmed level-2
        slope edge belonging to the surface and lying on the ground; returns its id."""
        bid = self._slope_edge(f"contact of {sid}", sid, t_ns)
        if self.ground_id is not None:
            self.ctx.record(Related(bid, "on_top_of", self.ground_id, t_ns))
        return bid

    def _slope_edge(self, name: str, sid: int, t_ns: int) -> int:
        """A new confirmed level-2 slope edge ``name`` belonging to surface ``sid`` (a
        contact with the ground or a crease); returns its id."""
        ctx = self.ctx
        lid = ctx.new_entity(
            name,
            Level.LIST,
            generic_classes=("slope_edge",) if "slope_edge" in ctx.classes else (),
            images=(IMAGE_NAMES[2],),
            status=Status.CONFIRMED,
            confidence=1.0,
        )
        ctx.record(Related(lid, "belongs_to", sid, t_ns))
        ctx.set_class(lid, "slope_edge")
        return lid

    def object_gone(self, oid: int) -> None:
        """Object ``oid`` went: its face and the face's contact boundary go with it."""
        for part in self.track_surface.pop(oid, ()):
            self.ctx.record(FrameChange(part, status=Status.GONE))

    # ------------------------------------------------------------------ free surfaces

    def free_surfaces(
        self,
        t_ns: int,
        image3: np.ndarray,
        contact: np.ndarray,
        xyz_g: np.ndarray,
        free: np.ndarray,
        ground: np.ndarray,
        T_world_ladar: np.ndarray,
        row_el: np.ndarray,
        free_px: np.ndarray,
    ) -> tuple[np.ndarray, list[int]]:
        """Level 3 beyond the ground and the objects: the ``free`` pixels (valid, not ground,
        in no confirmed object) are fitted with surface patches on a coarse grid (level 2),
        coplanar neighbouring patches grouped into surfaces (:func:`group_patches`), and each
        surface continued from the last sweeps by its plane and centroid
        (:class:`SurfaceTracker`) so its id persists, its plane and attributes filtered
        recursively; the confidence from its innovations confirms or denies it (a denied
        surface releases its pixels), and it is classified among the level-3 prototypes
        (ground, road, wall ...). Where two surfaces (or one and an object's face) meet at an
        angle, their crease is a level-2 list of both (:meth:`_creases`). Where a surface
        stands on the ground, its pixels just above a ground pixel are its contact boundary,
        a level-2 list belonging to the surface and lying on the ground (written into
        ``contact``, as are the creases). The surfaces' pixels are set in ``free_px``.
        Returns (image3 with the surfaces, their ids)."""
        ctx = self.ctx
        cfg = ctx.config
        H, W = free.shape
        tracker = self.surface_tracker
        for sid in tracker.forget(t_ns):
            self._surface_gone(int(sid))
        self._forget_creases(t_ns)
        grid = patch_grid(xyz_g, free, cfg.list_config)
        obs = group_patches(grid, 2 * math.pi / W, row_step(row_el), cfg.surfaces)
        if len(obs) == 0:
            return image3, []
        # the free pixels of the blocks grouped into surfaces, and their surface index
        px = np.flatnonzero(free.reshape(-1))
        row, col = np.divmod(px, W)
        bh, bw = grid.block
        lab = obs.label[(row // bh) * grid.shape[1] + col // bw]
        px, row, lab = px[lab >= 0], row[lab >= 0], lab[lab >= 0]
        c_w = obs.centroid + T_world_ladar[:3, 3]
        index = tracker.match(obs.normal, c_w, obs.area_m2)
        n_new = int(np.count_nonzero(index < 0))
        new_ids = np.array(
            [
                ctx.new_entity(
                    f"surface@{t_ns}",
                    Level.SURFACE,
                    images=(IMAGE_NAMES[3],),
                    status=Status.HYPOTHESIZED,
                    confidence=0.3,
                )
                for _ in range(n_new)
            ],
            dtype=np.int64,
        )
        ids = tracker.update(index, new_ids, obs, c_w, t_ns)
        row_k = tracker.rows(ids)
        status, conf = tracker.status[row_k], tracker.confidence[row_k]
        denied = status == TrackStatus.DENIED
        rows = [
            {
                "slope_rad": float(obs.slope_rad[k]),
                "roughness_m": float(obs.roughness_m[k]),
                "height_m": float(obs.height_m[k]),
                "area_m2": float(obs.area_m2[k]),
                "range_m": float(np.linalg.norm(obs.centroid[k])),
                "azimuth_rad": float(obs.azimuth_rad[k]),
                "n_pixels": float(obs.n_pixels[k]),
            }
            for k in range(len(obs))
        ]
        matches = self.classifier.classify_many(rows)
        ctx.set_classes(ids, [m.name for m in matches])
        was = self._surface_status.get
        changed = np.array([was(int(i)) != int(st) for i, st in zip(ids, status, strict=True)])
        due = ctx.due(ids) | (index < 0) | changed
        for k in np.flatnonzero(due & ~denied):
            sid = int(ids[k])
            self._surface_status[sid] = int(status[k])
            change = FrameChange(
                sid,
                attributes={n: Attribute(observed=v) for n, v in rows[k].items()},
                generic_classes=matches[k].generic,
                status=KD_STATUS[TrackStatus(int(status[k]))],
                confidence=unit(conf[k]),
            )
            ctx.record(change)
            ctx.record(StateObserved(sid, t_ns, c_w[k].copy(), np.zeros(3), StateRule.IF_NEWER))
        # a denied grouping hypothesis releases its pixels
        for sid in tracker.drop_denied():
            self._surface_gone(int(sid), Status.DENIED)
        keep = ~denied[lab]
        px, row, lab = px[keep], row[keep], lab[keep]
        free_px.reshape(-1)[px] = True
        # ground contact: a surface pixel just above a ground pixel
        low = row < H - 1
        touch = np.zeros(px.size, dtype=bool)
        touch[low] = ground.reshape(-1)[px[low] + W]
        if touch.any() and self.ground_id is not None:
            boundary = np.full(len(obs), -1, dtype=np.int64)
            for k in np.unique(lab[touch]):
                boundary[k] = self._contact_of(int(ids[k]), t_ns)
            contact.reshape(-1)[px[touch]] = boundary[lab[touch]]
        image3.reshape(-1)[px] = ids[lab]
        self._creases(t_ns, contact, image3, obs, ids, denied, xyz_g, free, grid)
        return image3, [int(i) for i in ids[~denied]]

    def _creases(
        self,
        t_ns: int,
        contact: np.ndarray,
        image3: np.ndarray,
        obs: SurfaceObservations,
        ids: np.ndarray,
        denied: np.ndarray,
        xyz_g: np.ndarray,
        free: np.ndarray,
        grid: PatchGrid,
    ) -> None:
        """Creases (:func:`find_creases`) between this sweep's free surfaces (``obs``, ids
        ``ids``, already in ``image3``) and with the objects' faces in ``image3``: one level-2
        ``slope_edge`` list per pair of surfaces (belonging to the free one, beside the
        other), written into ``contact`` on its pixels."""
        H, W = free.shape
        blocks = np.where(denied[np.maximum(obs.label, 0)], -1, obs.label)
        ent, normal, point = ids, obs.normal, obs.centroid
        faces = [f for f, _ in self.track_surface.values()]
        if faces:  # the objects' faces: their planes and blocks
            face_px = np.flatnonzero(np.isin(image3, faces))
            face_ids, face_lab = np.unique(image3.reshape(-1)[face_px], return_inverse=True)
            c_f, n_f, _ = plane_fit(face_lab, xyz_g.reshape(-1, 3)[face_px], face_ids.size)
            blk = grid.block_of_pixel(H, W).reshape(-1)[face_px]
            blocks[blk] = np.where(blocks[blk] < 0, len(obs) + face_lab, blocks[blk])
            ent, normal, point = np.r_[ids, face_ids], np.r_[normal, n_f], np.r_[point, c_f]
        if ent.size < 2:
            return
        cr = find_creases(
            blocks.reshape(grid.shape), grid.block, image3, free, xyz_g, ent, normal, point,
            self.ctx.config.surfaces, az_step_rad=2 * math.pi / W,
        )  # fmt: skip
        if len(cr):
            pairs = zip(ent[cr.a].tolist(), ent[cr.b].tolist(), strict=True)
            crease_ids = np.array([self._crease_of(a, b, t_ns) for a, b in pairs], np.int64)
            contact.reshape(-1)[cr.pixel] = crease_ids[cr.crease]

    def _forget_creases(self, t_ns: int) -> None:
        """Creases unseen for ``forget_s`` are gone."""
        forget_ns = self.ctx.config.surfaces.forget_s * 1e9
        for key, (lid, seen_ns) in list(self._crease.items()):
            if t_ns - seen_ns > forget_ns:
                self.ctx.record(FrameChange(lid, status=Status.GONE))
                del self._crease[key]

    def _crease_of(self, sid_a: int, sid_b: int, t_ns: int) -> int:
        """The crease list between surfaces ``sid_a`` and ``sid_b``, made on first sight: a
        slope edge belonging to ``sid_a`` and beside ``sid_b`` (the KD's belongs_to is a tree:
        one parent), its name naming both."""
        key = (min(sid_a, sid_b), max(sid_a, sid_b))
        if key not in self._crease:
            lid = self._slope_edge(f"crease of {key[0]} and {key[1]}", sid_a, t_ns)
            self.ctx.record(Related(lid, "beside", sid_b, t_ns))
            self._crease[key] = (lid, t_ns)
        lid = self._crease[key][0]
        self._crease[key] = (lid, t_ns)
        return lid

    def _contact_of(self, sid: int, t_ns: int) -> int:
        """The contact boundary list of free surface ``sid`` with the ground, made on first
        sight: it belongs to the surface and lies on the ground."""
        if sid not in self._surface_contact:
            self._surface_contact[sid] = self._contact_list(sid, t_ns)
        return self._surface_contact[sid]

    def _surface_gone(self, sid: int, status: Status = Status.GONE) -> None:
        """A free surface unseen for ``forget_s`` (or denied, ``status``): it and its lists
        are gone."""
        self.ctx.record(FrameChange(sid, status=status))
        self._surface_status.pop(sid, None)
        also = [self._surface_contact.pop(sid)] if sid in self._surface_contact else []
        self.lists.owner_gone(sid, also)


def vertical_face(a: SegmentAttributes, cfg: SPConfig) -> np.ndarray:
    """(K,) bool: segments that are a broad, thin plane within ``face_tilt_deg`` of vertical
    (a wall or a building side: a level-3 surface, reference 001, 4.5.6)."""
    upright = a.verticality <= math.sin(math.radians(cfg.face_tilt_deg))
    return upright & (a.breadth_m >= cfg.face_breadth_m) & (a.thickness_m <= cfg.face_thick_m)


def foot_rise_deg(
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
    """How steeply each segment rises from its foot (reference 001, 4.5.2: continuity).

    In every column where a segment's lowest return (its foot there) has a ground return next
    below it (across at most ``row_gap`` rows without a return), the segment's returns are
    followed up the column from the foot until one lies ``rise_m`` above it. The column's
    rise is the steeper of two angles above the horizontal (over 90 when the chord leans back
    towards the sensor): the first step up from the foot, and the chord from the foot to that
    return. A bank is gentle in both. A car's body starts above the road (its ground
    clearance) and its lower edge is rounded, so its first step may be gentle, but its side
    rises upright; a dome's top recedes gently, but its foot leans back over the ground (a
    bush's underside). A column counts only where each step (ground to foot, return to
    return) is at most ``max_chord_m`` long, so that the rows resolve the face (far out they
    lie metres apart), and ``rise_m`` is reached within ``max_rows`` returns, or half of it
    where the segment ends first in that column (the crest of a bank whose flank is ground).
    labels (H, W) int64 segment per pixel (-1 none); xyz_g (H, W, 3) gravity-aligned points
    centred on the sensor (m); has_return, ground (H, W) bool. Returns the median rise per
    segment (K,) float64 degrees (NaN where no column qualifies) and the number of columns
    (K,) int64.

    The walks up the columns are one compiled pass (:func:`_foot_walks`); the angles and
    medians stay numpy. ``tests/kernel_reference/level3_surfaces_reference.py`` holds the walk in
    numpy, and the two agree to the bit (tested).
    """
    lab, at_foot, at_first, at_top = _foot_walks(
        np.ascontiguousarray(labels, dtype=np.int64),
        np.ascontiguousarray(xyz_g, dtype=np.float64),
        np.ascontiguousarray(has_return, dtype=np.bool_),
        np.ascontiguousarray(ground, dtype=np.bool_),
        int(row_gap), float(max_chord_m), float(rise_m), int(max_rows),
    )  # fmt: skip

    def angle_to(at: np.ndarray) -> np.ndarray:
        return np.degrees(np.arctan2(at[:, 1] - at_foot[:, 1], at[:, 0] - at_foot[:, 0]))

    # a bank is gentle in both, a dome or a rounded car body steep in one of them
    angle = np.maximum(angle_to(at_first), angle_to(at_top))
    return _median_by_segment(lab, angle, n_segments)


def _median_by_segment(
    lab: np.ndarray, value: np.ndarray, n_segments: int
) -> tuple[np.ndarray, np.ndarray]:
    """The median of ``value`` (n,) float64 per segment of ``lab`` (n,) int64 in
    0..n_segments-1: (K,) float64 (NaN where a segment has none), and the count (K,) int64."""
    count = np.bincount(lab, minlength=n_segments)
    median = np.full(n_segments, np.nan)
    if lab.size:
        order = np.lexsort((value, lab))
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        has = count > 0
        lo = start[has] + (count[has] - 1) // 2
        hi = start[has] + count[has] // 2
        median[has] = 0.5 * (value[order][lo] + value[order][hi])
    return median, count


@numba.njit(cache=True, nogil=True)
def _next_row(has, i, j, step, gap):  # pragma: no cover
    """Row of the next return from pixel (i, j) along its column of ``has`` (H, W) bool,
    ``step`` +1 down or -1 up, across at most ``gap`` rows without one; -1 if none."""
    for k in range(1, gap + 2):
        r = i + step * k
        if r < 0 or r >= has.shape[0]:
            return -1
        if has[r, j]:
            return r
    return -1


@numba.njit(cache=True, nogil=True)
def _foot_walks(labels, xyz_g, has, ground, gap, max_chord_m, rise_m, max_rows):  # pragma: no cover
    """The walks of :func:`foot_rise_deg`, one per foot (a segment's pixel whose next return
    down is ground), in row-major order. Returns, for the feet whose column counts: the
    segment (n,) int64, and (n, 2) float64 (horizontal range, z) of the foot, of the first
    return up from it and of the last one reached."""
    H, W = labels.shape
    n = 0
    for i in range(H):
        for j in range(W):
            n += labels[i, j] >= 0
    lab = np.empty(n, np.int64)
    at = np.empty((3, n, 2))  # foot, first step, top
    m = 0
    for i in range(H):
        for j in range(W):
            s = labels[i, j]
            if s < 0:
                continue
            g = _next_row(has, i, j, 1, gap)
            if g < 0 or not ground[g, j]:
                continue
            f_hr, f_z = np.hypot(xyz_g[i, j, 0], xyz_g[i, j, 1]), xyz_g[i, j, 2]
            g_hr, g_z = np.hypot(xyz_g[g, j, 0], xyz_g[g, j, 1]), xyz_g[g, j, 2]
            alive = np.hypot(f_hr - g_hr, f_z - g_z) <= max_chord_m
            top, t_hr, t_z = i, f_hr, f_z
            a_hr, a_z = f_hr, f_z
            reached = ended = False
            for step in range(max_rows):
                if not alive or reached or ended:
                    break
                r = _next_row(has, top, j, -1, gap)
                if r < 0 or labels[r, j] != s:
                    ended = True
                    break
                n_hr, n_z = np.hypot(xyz_g[r, j, 0], xyz_g[r, j, 1]), xyz_g[r, j, 2]
                if not np.hypot(n_hr - t_hr, n_z - t_z) <= max_chord_m:
                    alive = False
                    break
                top, t_hr, t_z = r, n_hr, n_z
                if step == 0:
                    a_hr, a_z = t_hr, t_z
                reached = t_z - f_z >= rise_m
            # a segment lower than rise_m above its foot (the crest of a bank whose flank is
            # ground) counts from half of it
            if alive and (reached or (ended and t_z - f_z >= 0.5 * rise_m)):
                lab[m] = s
                at[0, m, 0], at[0, m, 1] = f_hr, f_z
                at[1, m, 0], at[1, m, 1] = a_hr, a_z
                at[2, m, 0], at[2, m, 1] = t_hr, t_z
                m += 1
    return lab[:m], at[0, :m], at[1, :m], at[2, :m]


def terrain_patch(a: SegmentAttributes, cfg: SPConfig) -> np.ndarray:
    """(K,) bool: segments that are a broad, thin plane tilted less than ``terrain_tilt_deg``,
    lower than ``terrain_max_height_m`` (a roof is higher) and starting within
    ``terrain_clearance_m`` of the ground under it (a car's hood does not): level 3 surfaces
    of the ground (reference 001, 4.5.6), not objects standing on it."""
    flat = a.verticality >= math.cos(math.radians(cfg.terrain_tilt_deg))
    plane = (a.breadth_m >= cfg.terrain_breadth_m) & (a.thickness_m <= cfg.terrain_thick_m)
    low = (a.height_m < cfg.terrain_max_height_m) & (a.clearance_m <= cfg.terrain_clearance_m)
    return flat & plane & low

"""Sensory processing levels 2 to 5: one LADAR sweep in, entity and event frames into the KD.

Reference 001, 4.5.1-4.5.4 (the five SP functions: windowing, grouping, computation,
filtering, classification; hypothesize and test; recursive estimation), 4.4.4-4.4.5 (entity
images whose pixels hold frame ids, frames that point back to their images), 4.5.6 (levels 2
to 5). One call of :meth:`SensoryProcessor.process` is one cycle:

1. egosphere image of the sweep (level 1, :mod:`sp.egosphere`), points to the world frame;
2. level 3: the ground surface (:mod:`sp.ground`), one persistent ground entity; segments that
   are bumps sitting low on it or broad gentle planes near it join it (:func:`terrain_patch`);
3. level 4: object hypotheses grouped from the rest (:mod:`sp.segments`: contiguity, then line
   continuity), their attributes (:mod:`sp.computation`), association with the predicted
   tracks (confirmed ones first) and Kalman updates, confirm / deny (:mod:`sp.tracking`),
   classification (:mod:`sp.classify`). A hypothesis gets a KD frame and an "appeared" event
   only once seen ``birth_hits`` times (M-of-N birth); until then it draws attention only;
4. level 3 beyond the ground: the vertical planar face of a confirmed object is a surface
   entity (part of the object), its contact with the ground a level-2 list; the pixels in no
   confirmed object and not ground are fitted with level-2 surface patches that group into
   free-standing surfaces (walls, building fronts, slopes: :mod:`sp.surfaces`), tracked from
   sweep to sweep, each with its ground-contact boundary;
5. level 2: range edges, brightness edges, vertices and surface patches (:mod:`sp.lists`),
   one list entity per (owner, kind) (:meth:`SensoryProcessor._lists` says why);
6. level 5: groups of objects (:mod:`sp.groups`);
7. entity images per level, entity frames, pointers and events (:mod:`sp.events`) in the KD;
   class images per level and value images (:mod:`sp.images`);
8. with a camera frame: the confirmed objects' appearance (:mod:`sp.appearance`).

Deskewing: ``T_world_ladar`` is the sensor pose at ``pose_t_ns`` (the sweep's stamp unless the
caller says otherwise). Each column of the image fired at its own time; its points go to the
world with the pose at that time, interpolated (or extrapolated) at constant velocity between
the previous sweep's pose and this one (:func:`column_poses`), so a static object does not
smear or jump by the vehicle's motion during the sweep (up to a metre at 10 m/s). The first
sweep, or one after a gap of more than ``deskew_max_gap_s``, is taken at the one pose. Each
object's state is stamped at the mean time of its own returns.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

import kd_store
from core.errors import EngineError
from core.geometry import check_pose, interpolate_pose, matrix_to_quat, rot_z
from kd_store import Attribute, Level, StateBatch, Status
from logs.types import CameraFrame, LadarScan
from sp.appearance import object_appearance
from sp.classify import Classifier, ClassifyConfig
from sp.computation import SegmentAttributes, ground_below, ground_plane, segment_attributes
from sp.egosphere import EgosphereConfig, EgosphereImage, to_egosphere
from sp.events import EventClass, emit
from sp.ground import GroundConfig, ground_mask
from sp.groups import GroupConfig, group_labels, match_groups
from sp.images import ClassTable, LazyImages, class_image, class_values, value_images
from sp.lists import (
    KIND_CLASS,
    ListConfig,
    ListKind,
    PatchGrid,
    brightness_edges,
    fill_slots,
    list_attributes,
    list_slots_and_sums,
    list_sums,
    mean_intensity,
    patch_grid,
)
from sp.segments import (
    SegmentConfig,
    label_objects,
    merge_collinear,
    merge_grazing,
    range_edges,
    split_by_predictions,
)
from sp.surfaces import (
    SurfaceConfig,
    SurfaceObservations,
    SurfaceTracker,
    find_creases,
    group_patches,
    plane_fit,
)
from sp.sweep_points import sweep_points
from sp.tracking import Measurements, Tracker, TrackerConfig, TrackStatus, evident_speed
from sp.windowing import WindowConfig, window_mask

log = logging.getLogger(__name__)

IMAGE_NAMES = {2: "sp2_lists", 3: "sp3_surfaces", 4: "sp4_objects", 5: "sp5_groups"}
# shape attributes of an object's points, observed per sweep (sp.computation.SegmentAttributes,
# same names) and averaged per object; the last, ``longest_m``, is the longest extent the object
# was seen with (it grows as more of a wall comes into view)
SHAPE_KEYS = ("thickness_m", "curvature", "verticality", "breadth_m", "clearance_m", "longest_m")
_SURFACE_KEYS = 3  # the first three describe a surface of points, not a line (_observe_shape)
SHAPE_MIN_BREADTH_M = 0.05  # a segment's points spread this far along its middle axis ...
SHAPE_MIN_PIXELS = 12  # ... in this many returns at least, or its thickness is unknown
# classes of objects that move by themselves: only they link as moving members of a group
MOBILE_CLASSES = frozenset({"vehicle", "person"})

_STATUS = {
    TrackStatus.HYPOTHESIZED: Status.HYPOTHESIZED,
    TrackStatus.CONFIRMED: Status.CONFIRMED,
    TrackStatus.DENIED: Status.DENIED,
    TrackStatus.GONE: Status.GONE,
}


class PipelineError(EngineError, ValueError):
    """A sweep or pose the pipeline cannot use; names the value and the sweep's time."""


@dataclass(frozen=True)
class SPConfig:
    """Every parameter of SP levels 2-5, with its default, in one place."""

    egosphere: EgosphereConfig = field(
        default_factory=lambda: EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1)
    )
    ground: GroundConfig = field(default_factory=GroundConfig)
    segments: SegmentConfig = field(default_factory=SegmentConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    classify: ClassifyConfig = field(default_factory=ClassifyConfig)
    groups: GroupConfig = field(default_factory=GroupConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    birth_hits: int = 2  # a hypothesis gets a KD frame (and "appeared") after this many hits
    min_pixels_attended: int = 2  # smallest hypothesis inside an attention window
    max_object_range_m: float = 120.0  # farther segments are left ungrouped
    min_object_height_m: float = 0.5  # lower segments are ground (bumps, ruts, curbs)
    # a segment holding two tracked people's predicted places (each within split_near_m of
    # its returns, at least split_min_apart_m apart) is cut between them
    split_near_m: float = 0.4
    split_min_apart_m: float = 0.5
    reclassify_margin: float = 0.05  # score gain needed to change a confirmed class
    found_specific: bool = True  # a confirmed object matching nothing founds a specific class
    lists: bool = True  # level-2 list entities (edges, vertices, patches)
    list_config: ListConfig = field(default_factory=ListConfig)
    free_surfaces: bool = True  # level-3 surfaces beyond the ground and the objects' faces
    surfaces: SurfaceConfig = field(default_factory=SurfaceConfig)
    kd_refresh_sweeps: int = 8  # list and surface frames rewritten every this many sweeps
    appearance_classes: bool = True  # objects classified with their observed appearance too
    # LADAR intensity units of a unit reflectance: 1.0 for sensors that report reflectance
    # 0..1 (the simulator, KITTI); None (unknown units) leaves the LADAR intensity out of
    # classification, since a wrong scale would mislead it; the camera's grey is 0..1 always
    intensity_per_reflectance: float | None = None
    appearance_gain: float = 0.3  # running-mean gain of an object's observed appearance
    terrain_tilt_deg: float = 25.0  # a broad thin plane tilted less than this is ground ...
    terrain_breadth_m: float = 0.25  # ... when its points spread this far along its middle axis
    terrain_thick_m: float = 0.12  # ... and this little across its plane (std, m)
    terrain_max_height_m: float = 1.2  # ... and it rises less than this over the ground
    terrain_clearance_m: float = 0.3  # ... from no higher than this above it (a car's hood is)
    face_tilt_deg: float = 20.0  # a plane within this of vertical is a face (level 3) ...
    face_breadth_m: float = 0.3  # ... when its points spread this far along its middle axis
    face_thick_m: float = 0.15  # ... and this little across it (std, m)
    deskew_max_gap_s: float = 0.5  # no constant-velocity deskew over a longer gap between poses


@dataclass
class SPResult:
    """What one cycle produced (arrays on the LADAR egosphere image grid, (H, W)).

    entity_images:     SP level -> (H, W) int64 frame ids, -1 none.
    class_images:      SP level -> (H, W) int32 index into ``class_names`` of each pixel's
                       entity's class at that level, -1 none (reference 001, 4.4.4); made
                       on first access (a read-only mapping).
    value_images:      value name (cost, risk, worth_preserve) -> (H, W) float32 value of the
                       class of each pixel's level-4 entity, else its level-3 entity (the
                       class library's ``value``), NaN where the pixel has neither.
    surfaces:          ids of the free-standing level-3 surfaces observed this cycle.
    ground_mask:       (H, W) bool.
    points_world:      (N, 3) float32 world points of the image's valid pixels (row-major).
    point_entity_ids:  (N,) int64 level-4 object id per point, -1 none.
    point_class_ids:   (N,) int32 index into ``class_names`` (-1 none): the class of the
                       point's object, else of its level-3 surface (ground, face, wall ...).
    objects:           ids of the level-4 entities observed this cycle.
    events:            ids of the event frames emitted this cycle.
    timings_s:         seconds per stage.
    point_pixel:       (N,) int64 flat pixel index of each point; point_index (N,) its index
                       in the sweep.
    attention_mask:    (H, W) bool windows used this cycle.
    class_names:       the class names ``point_class_ids`` index.
    ok:                False when the sweep failed and was skipped (tracks kept).
    """

    t_ns: int
    entity_images: dict[int, np.ndarray]
    ground_mask: np.ndarray
    points_world: np.ndarray
    point_entity_ids: np.ndarray
    point_class_ids: np.ndarray
    objects: list[int]
    events: list[int]
    timings_s: dict[str, float]
    point_pixel: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    point_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    attention_mask: np.ndarray | None = None
    class_names: list[str] = field(default_factory=list)
    class_images: Mapping[int, np.ndarray] = field(default_factory=dict)
    value_images: Mapping[str, np.ndarray] = field(default_factory=dict)
    surfaces: list[int] = field(default_factory=list)
    ok: bool = True


class _Clock:
    def __init__(self) -> None:
        self.t = time.perf_counter()
        self.laps: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = self.laps.get(name, 0.0) + now - self.t
        self.t = now


def _row_step(row_el: np.ndarray) -> float:
    ok = np.flatnonzero(np.isfinite(row_el))
    if ok.size < 2:
        return math.radians(1.0)
    d = -np.diff(row_el[ok]) / np.diff(ok)
    d = d[d > 0]
    return float(np.median(d)) if d.size else math.radians(1.0)


class SensoryProcessor:
    """SP levels 2-5 over LADAR sweeps, writing entity and event frames into ``kd``."""

    def __init__(self, kd: kd_store.KnowledgeDatabase, config: SPConfig | None = None) -> None:
        self.kd = kd
        self.config = config or SPConfig()
        self.tracker = Tracker(self.config.tracker)
        self.classifier = Classifier(kd.classes, Level.OBJECT, self.config.classify)
        self.class_names = [p.name for p in kd.classes]
        self._class_index = {n: i for i, n in enumerate(self.class_names)}
        self.ground_id: int | None = None
        self.track_class: dict[int, tuple[str | None, float]] = {}
        self.track_reflectance: dict[int, float] = {}  # object id -> mean LADAR intensity
        self.track_camera: dict[int, float] = {}  # object id -> mean camera grey (0..1)
        self.track_shape: dict[int, np.ndarray] = {}  # object id -> running shape (SHAPE_KEYS)
        self.class_table = ClassTable()  # entity id -> class index, for the class images
        self._list_lut = np.full(1024, -1, dtype=np.int64)  # owner * 4 + kind -> list slot
        self._list_ids = np.zeros(0, dtype=np.int64)  # list slot -> list frame id
        self._lists_of: dict[int, list[int]] = {}  # owner id -> its list ids
        # per list slot: recursive confidence, sweeps seen, and whether still hypothesized
        self._list_conf = np.zeros(0)
        self._list_hits = np.zeros(0, dtype=np.int64)
        self._list_open = np.zeros(0, dtype=bool)
        self._list_key = np.zeros(0, dtype=np.int64)  # slot -> owner * 4 + kind
        self._list_dead = np.zeros(0, dtype=bool)  # denied: its key makes a new list if seen
        self._sensor_xy: np.ndarray | None = None  # the sensor's world xy this sweep
        self._list_classifier = Classifier(kd.classes, Level.LIST, self.config.classify)
        self.surface_tracker = SurfaceTracker(self.config.surfaces)
        self._surface_contact: dict[int, int] = {}  # free surface id -> its contact list id
        self._surface_status: dict[int, int] = {}  # free surface id -> status written to KD
        self._crease: dict[tuple[int, int], tuple[int, int]] = {}  # surfaces -> (list, t_ns)
        self._free_px = np.zeros((0, 0), dtype=bool)
        self._values: tuple[int, dict[str, np.ndarray]] = (-1, {})
        self._sweep = 0
        self.track_surface: dict[int, tuple[int, int]] = {}  # object -> (face, contact) ids
        self._surface_classifier = Classifier(kd.classes, Level.SURFACE, self.config.classify)
        self.groups: dict[int, frozenset[int]] = {}
        self._group_hits: dict[int, int] = {}  # cycles each group has been seen
        self._attention = np.zeros((0, 0), dtype=bool)
        self._last_pose: tuple[int, np.ndarray] | None = None
        self._next_provisional = -2  # ids of hypotheses without a frame yet: -2, -3, ...
        self._provisional_segments = np.zeros(0, np.int64)
        self.n_failed = 0

    # ------------------------------------------------------------------ the cycle

    def process(
        self,
        scan: LadarScan,
        T_world_ladar: np.ndarray,
        *,
        camera: CameraFrame | None = None,
        T_world_camera: np.ndarray | None = None,
        attention_world_xyz: np.ndarray | None = None,
        pose_t_ns: int | None = None,
    ) -> SPResult:
        """One cycle on one sweep (points in the sensor frame, ``T_world_ladar`` the sensor pose
        at ``pose_t_ns``, by default ``scan.t_ns``). A sweep that fails is logged and skipped;
        the tracks are kept. With a camera frame and its pose, each confirmed object's returns
        are projected into it for its camera intensity and coverage (:mod:`sp.appearance`); a
        camera frame that fails is logged and skipped, the sweep's result kept."""
        try:
            T = check_pose(np.asarray(T_world_ladar, dtype=np.float64), "T_world_ladar")
            t_pose = int(scan.t_ns if pose_t_ns is None else pose_t_ns)
            result = self._process(scan, T, t_pose, attention_world_xyz)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as e:
            return self._failed(scan, e)
        if camera is not None and T_world_camera is not None:
            try:
                self._appearance(result, camera, T_world_camera)
            except (ValueError, np.linalg.LinAlgError) as e:  # the camera frame is skipped
                self.n_failed += 1
                log.warning("SP skipped the camera frame at t_ns=%s: %s", camera.t_ns, e)
        return result

    def _failed(self, scan: LadarScan, e: Exception) -> SPResult:
        """An empty result for a sweep that failed (logged; the tracks are kept)."""
        self.n_failed += 1
        log.warning("SP skipped the sweep at t_ns=%s: %s", getattr(scan, "t_ns", "?"), e)
        H, W = self.config.egosphere.n_rows, self.config.egosphere.n_cols
        return SPResult(
            t_ns=int(getattr(scan, "t_ns", 0)),
            entity_images={k: np.full((H, W), -1, np.int64) for k in IMAGE_NAMES},
            ground_mask=np.zeros((H, W), bool),
            points_world=np.zeros((0, 3), np.float32),
            point_entity_ids=np.zeros(0, np.int64),
            point_class_ids=np.zeros(0, np.int32),
            objects=[],
            events=[],
            timings_s={},
            class_names=self.class_names,
            ok=False,
        )

    def _process(
        self,
        scan: LadarScan,
        T_world_ladar: np.ndarray,
        pose_t_ns: int,
        attention_world_xyz: np.ndarray | None,
    ) -> SPResult:
        cfg = self.config
        clock = _Clock()
        t_ns = int(scan.t_ns)
        events: list[int] = []
        # level 1: the egosphere image and its points in the world and gravity-aligned frames
        img = to_egosphere(scan, cfg.egosphere)
        valid = img.valid_first
        H, W = valid.shape
        T_cols = self._column_poses(img, t_ns, T_world_ladar, pose_t_ns)
        xyz_s, xyz_g, xyz_w, row_el = sweep_points(img, T_world_ladar[:3, :3], T_cols)
        rng = np.where(valid, img.range_first, np.inf)
        clock.lap("egosphere")

        # level 3: the ground
        ground, _h = ground_mask(xyz_g, valid, cfg.ground)
        clock.lap("ground")

        # windowing: predicted tracks (window by uncertainty), attention points, last cycle's
        # unexplained pixels
        attention = self._windows((H, W), T_world_ladar, row_el, t_ns, attention_world_xyz)
        clock.lap("windowing")

        # level 4 grouping
        cand = valid & ~ground & (rng <= cfg.max_object_range_m)
        seg_cfg = cfg.segments
        labels = label_objects(
            xyz_s, rng, cand, _row_step(row_el), 2 * math.pi / W, _with_min(seg_cfg, 1)
        )
        labels = _drop_small(labels, attention, seg_cfg.min_pixels, cfg.min_pixels_attended)
        clock.lap("grouping")

        gz = ground_below(ground, xyz_w[..., 2], np.hypot(xyz_g[..., 0], xyz_g[..., 1]))
        inten = np.nan_to_num(img.intensity[..., 0])
        rng0 = np.where(valid, img.range_first, 0.0)
        t_off = img.t_offset_ns[..., 0]
        attrs = segment_attributes(labels, xyz_w, inten, rng0, t_off, gz)
        # a face seen at a grazing angle breaks into strips along the line of sight: one face
        grazed = merge_grazing(
            attrs.center_xyz[:, :2], attrs.width_m, attrs.ground_z_m + attrs.height_m,
            T_world_ladar[:2, 3], 2 * math.pi / W, seg_cfg,
        )  # fmt: skip
        if grazed.size and grazed.max() + 1 < len(attrs):
            labels = np.where(labels >= 0, grazed[np.maximum(labels, 0)], -1)
            attrs = segment_attributes(labels, xyz_w, inten, rng0, t_off, gz)
        # continuity: pieces of one wall or fence cut by occluders are one object
        merged = merge_collinear(
            attrs.center_xyz[:, :2], attrs.yaw_rad, attrs.length_m, attrs.width_m,
            attrs.range_m, seg_cfg,
        )  # fmt: skip
        if merged.size and merged.max() + 1 < len(attrs):
            labels = np.where(labels >= 0, merged[np.maximum(labels, 0)], -1)
            attrs = segment_attributes(labels, xyz_w, inten, rng0, t_off, gz)
        # people walking side by side, joined by proximity, are cut where their tracks predict
        split = split_by_predictions(
            labels, xyz_w, self._predicted_people_xy(t_ns), attrs.center_xyz[:, :2],
            0.5 * np.hypot(attrs.length_m, attrs.width_m), cfg.split_near_m,
            cfg.split_min_apart_m, seg_cfg.min_pixels,
        )  # fmt: skip
        if split is not labels:
            labels = split
            attrs = segment_attributes(labels, xyz_w, inten, rng0, t_off, gz)
        # too low to stand out of the terrain (bumps, ruts), or a gently sloping plane (a
        # hillside seen past a gap): ground, not objects
        low = (attrs.height_m < cfg.min_object_height_m) | terrain_patch(attrs, cfg)
        if low.any():
            flat_low = np.isin(labels, np.flatnonzero(low))
            ground = ground | flat_low
            remap = np.full(len(attrs), -1, dtype=np.int64)
            remap[~low] = np.arange(int((~low).sum()))
            labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
            attrs = attrs.take(~low)
        clock.lap("computation")

        # filtering: associate with the predictions, update, confirm or deny
        self._sensor_xy = T_world_ladar[:2, 3].copy()  # partial views lie on its side
        obj_ids, events_f = self._filter(attrs, t_ns)
        events += events_f
        clock.lap("filtering")

        # classification
        events += self._classify(t_ns)
        clock.lap("classification")

        # entity images and frames
        image4 = np.full((H, W), -1, dtype=np.int64)
        has = labels >= 0
        image4[has] = obj_ids[labels[has]]
        denied = self._denied_ids
        if denied.size:
            image4[np.isin(image4, denied)] = -1  # a denied hypothesis releases its pixels
        image3 = np.full((H, W), -1, dtype=np.int64)
        image3[ground] = self._ground_entity(t_ns, xyz_w, ground, T_world_ladar)
        image3, contact = self._surfaces(t_ns, image3, labels, attrs, obj_ids, ground)
        in_object = self._confirmed_pixels(image4)
        surfaces: list[int] = []
        self._free_px = np.zeros((H, W), dtype=bool)  # pixels of free surfaces (patches)
        if cfg.free_surfaces:
            free = valid & ~ground & ~in_object & (image3 < 0)
            image3, surfaces = self._free_surfaces(
                t_ns, image3, contact, xyz_g, free, ground, T_world_ladar, row_el
            )
        clock.lap("level3")
        image2 = np.full((H, W), -1, dtype=np.int64)
        if cfg.lists:
            owner = np.where(in_object, image4, image3)
            image2 = self._lists(t_ns, owner, rng, valid, img.intensity[..., 0])
        image2[contact >= 0] = contact[contact >= 0]
        self._sweep += 1
        clock.lap("level2")
        image5, events_g = self._groups(t_ns, image4)
        events += events_g
        clock.lap("groups")

        # unexplained: new and provisional hypotheses draw attention in the next cycle
        provisional = np.isin(labels, self._provisional_segments)
        self._attention = (has & np.isin(image4, self._born_ids)) | provisional
        flat = np.flatnonzero(valid.reshape(-1))
        pe = image4.reshape(-1)[flat]
        entity_images = {2: image2, 3: image3, 4: image4, 5: image5}
        class_images, values, point_class = self._class_images(entity_images, flat)
        result = SPResult(
            t_ns=t_ns,
            entity_images=entity_images,
            class_images=class_images,
            value_images=values,
            surfaces=surfaces,
            ground_mask=ground,
            points_world=xyz_w.reshape(-1, 3)[flat].astype(np.float32),
            point_entity_ids=pe,
            point_class_ids=point_class,
            objects=[int(i) for i in np.unique(pe[pe >= 0])],
            events=events,
            timings_s={},
            point_pixel=flat.astype(np.int64),
            point_index=img.point_index[..., 0].reshape(-1)[flat].astype(np.int64),
            attention_mask=attention,
            class_names=self.class_names,
        )
        clock.lap("images")
        result.timings_s = clock.laps
        return result

    def _appearance(self, r: SPResult, camera: CameraFrame, T_world_camera: np.ndarray) -> None:
        """Camera intensity and coverage of the confirmed objects of this cycle into the KD."""
        tr = self.tracker.tracks
        confirmed = tr.id[(tr.status == TrackStatus.CONFIRMED) & (tr.id >= 0)]
        sel = np.isin(r.point_entity_ids, confirmed)
        if not sel.any():
            return
        a = object_appearance(r.points_world[sel], r.point_entity_ids[sel], camera, T_world_camera)
        for oid, inten, cov in zip(a.ids, a.intensity, a.coverage, strict=True):
            attrs = dict(self.kd.get(int(oid)).attributes)
            attrs["camera_intensity"] = Attribute(observed=float(inten), observed_var=0.01)
            attrs["camera_coverage"] = Attribute(observed=float(cov))
            self._observe_appearance(self.track_camera, int(oid), float(inten))
            self.kd.update_entity(int(oid), attributes=attrs)

    def _column_poses(
        self, img: EgosphereImage, t_ns: int, T_world_ladar: np.ndarray, pose_t_ns: int
    ) -> np.ndarray:
        """(W, 4, 4) sensor pose at each column's firing time, through the last sweep's pose
        and this one; (1, 4, 4) this pose alone for the first sweep or after a gap."""
        last, self._last_pose = self._last_pose, (pose_t_ns, T_world_ladar)
        gap_ns = pose_t_ns - last[0] if last is not None else 0
        if last is None or not 0 < gap_ns <= self.config.deskew_max_gap_s * 1e9:
            return T_world_ladar[None]
        return column_poses(img, t_ns, last[1], last[0], T_world_ladar, pose_t_ns)

    # ------------------------------------------------------------------ windowing

    def _predicted_people_xy(self, t_ns: int) -> np.ndarray:
        """World xy (C, 2) m of the confirmed tracks classified person, predicted to ``t_ns``."""
        tr = self.tracker.tracks
        if not len(tr):
            return np.zeros((0, 2))
        people = np.array(
            [self.track_class.get(int(i), (None, 0.0))[0] == "person" for i in tr.id], dtype=bool
        ) & (tr.status == TrackStatus.CONFIRMED)
        if not people.any():
            return np.zeros((0, 2))
        x, _ = self.tracker.predicted(t_ns)
        return x[people, :2]

    def _windows(
        self,
        shape: tuple[int, int],
        T_world_ladar: np.ndarray,
        row_el: np.ndarray,
        t_ns: int,
        attention_world_xyz: np.ndarray | None,
    ) -> np.ndarray:
        tr = self.tracker.tracks
        centres, sig = [], []
        if len(tr):
            x, P = self.tracker.predicted(t_ns)
            centres.append(x[:, :3])
            sig.append(np.sqrt(np.maximum(P[:, 0, 0] + P[:, 1, 1], 0.0)))
        if attention_world_xyz is not None and len(attention_world_xyz):
            a = np.asarray(attention_world_xyz, dtype=np.float64).reshape(-1, 3)
            centres.append(a)
            sig.append(np.zeros(a.shape[0]))
        mask = np.zeros(shape, dtype=bool)
        if centres:
            c_w = np.concatenate(centres)
            R, t = T_world_ladar[:3, :3], T_world_ladar[:3, 3]
            c_s = (c_w - t) @ R  # world -> sensor
            mask = window_mask(shape, c_s, np.concatenate(sig), row_el, self.config.window)
        if self._attention.shape == shape:
            mask |= self._attention
        return mask

    # ------------------------------------------------------------------ filtering

    def _filter(self, a: SegmentAttributes, t_ns: int) -> tuple[np.ndarray, list[int]]:
        """Track the segments; returns (object id per segment (K,), event ids)."""
        kd = self.kd
        cfg = self.config
        what = np.stack([a.length_m, a.width_m, a.height_m, a.yaw_rad], axis=1)
        meas = Measurements(a.center_xyz, t_ns + a.t_offset_ns, what, a.range_m)

        def provisional_ids(n: int) -> np.ndarray:
            # a new hypothesis has no KD frame until it has been seen ``birth_hits`` times
            start = self._next_provisional
            self._next_provisional -= n
            return np.arange(start, start - n, -1, dtype=np.int64)

        track_of, prev = self.tracker.step(meas, t_ns, provisional_ids, self._sensor_xy)
        tr = self.tracker.tracks
        # M-of-N birth: hypotheses seen often enough get their frame (and "appeared") now; the
        # KD makes the frame first, so images, tracks and frames share the id
        promote = np.flatnonzero(
            (tr.id < 0)
            & ((tr.hits >= cfg.birth_hits) | (tr.status == TrackStatus.CONFIRMED))
            & (tr.status != TrackStatus.DENIED)
        )
        born: list[int] = []
        for k in promote:
            f = kd.add_entity(
                f"object@{t_ns}",
                Level.OBJECT,
                images=(IMAGE_NAMES[4],),
                confidence=_unit(tr.confidence[k]),
            )
            tr.id[k] = f.id
            prev[k] = -1
            born.append(f.id)
        self._born_ids = np.array(born, dtype=np.int64)
        events: list[int] = []
        for i in born:
            events.append(emit(kd, EventClass.APPEARED, t_ns, [i], 4, cfg.tracker.confidence0))
        # only tracks with a frame are written: provisional ones stay inside the tracker
        framed = tr.id >= 0
        track_of = np.where(
            track_of >= 0, np.where(framed[np.maximum(track_of, 0)], track_of, -2), -1
        )
        # states of the tracks updated this cycle
        upd = np.unique(track_of[track_of >= 0])
        # tracks the stationarity test finds at rest are reported at zero speed
        x_rep, P_rep = tr.reported(cfg.tracker)
        if upd.size:
            yaw = tr.w[upd, 3]
            moving = np.hypot(x_rep[upd, 3], x_rep[upd, 4]) > 1.0
            yaw = np.where(moving, np.arctan2(x_rep[upd, 4], x_rep[upd, 3]), yaw)
            q = np.stack([matrix_to_quat(rot_z(float(y))) for y in yaw])
            var_rpy = np.zeros((upd.size, 3))
            var_rpy[:, 2] = tr.Pw[upd, 3]
            kd.ingest(
                StateBatch(
                    tr.id[upd].copy(),
                    tr.t_ns[upd].copy(),
                    "world",
                    x_rep[upd, :3],
                    q,
                    x_rep[upd, 3:],
                    P_rep[upd],
                    var_rpy,
                )
            )
        # frames: status, confidence, attributes
        seg_of_track = np.full(len(tr), -1, dtype=np.int64)
        seg_of_track[track_of[track_of >= 0]] = np.flatnonzero(track_of >= 0)
        for k in np.flatnonzero(framed):
            tid = int(tr.id[k])
            status = _STATUS[TrackStatus(int(tr.status[k]))]
            was = int(prev[k])
            changes: dict[str, object] = {"status": status, "confidence": _unit(tr.confidence[k])}
            s = seg_of_track[k]
            if s >= 0:
                changes["attributes"] = _attributes(a, s, tr.w[k], tr.Pw[k], x_rep[k])
                self._observe_appearance(self.track_reflectance, tid, float(a.intensity[s]))
                self._observe_shape(tid, a, int(s))
            kd.update_entity(tid, **changes)
            if was == int(status_code(status)) or (was < 0 and status == Status.HYPOTHESIZED):
                continue
            cls = {
                Status.CONFIRMED: EventClass.CONFIRMED,
                Status.DENIED: EventClass.DENIED,
                Status.GONE: EventClass.VANISHED,
            }.get(status)
            if cls is not None:
                events.append(emit(kd, cls, t_ns, [tid], 4, float(tr.confidence[k])))
        finished = self.tracker.drop_finished()
        self._denied_ids = finished.id[(finished.status == TrackStatus.DENIED) & (finished.id >= 0)]
        for tid in finished.id:
            self.track_class.pop(int(tid), None)
            self.track_reflectance.pop(int(tid), None)
            self.track_camera.pop(int(tid), None)
            self.track_shape.pop(int(tid), None)
            for part in self.track_surface.pop(int(tid), ()):
                kd.update_entity(part, status=Status.GONE)  # the object's face goes with it
            self._parts_gone(self._lists_of.pop(int(tid), ()))  # and its lists
        self._provisional_segments = np.flatnonzero(track_of == -2)
        # object id per segment
        ids_all = np.concatenate([tr.id])
        obj = np.full(len(meas), -1, dtype=np.int64)
        ok = track_of >= 0
        obj[ok] = ids_all[track_of[ok]]
        return obj, events

    # ------------------------------------------------------------------ classification

    def _classify(self, t_ns: int) -> list[int]:
        kd = self.kd
        tr = self.tracker.tracks
        events: list[int] = []
        ks = np.flatnonzero(tr.id >= 0)
        speeds = evident_speed(tr.x[ks], tr.P[ks], self.config.tracker.evident_sigmas)
        rows = []
        for k, speed in zip(ks, speeds.tolist(), strict=True):
            l, w, h = (float(v) for v in tr.w[k, :3])
            rows.append(
                {"height_m": h, "width_m": w, "length_m": l, "speed_mps": speed}
                | self._appearance_of(int(tr.id[k]))
                | self._shape_of(int(tr.id[k]))
            )
        # all at once (a class founded below takes part from the next sweep on)
        for k, m in zip(ks, self.classifier.classify_many(rows), strict=True):
            tid = int(tr.id[k])
            old, _ = self.track_class.get(tid, (None, -2.0))
            confirmed = tr.status[k] == TrackStatus.CONFIRMED
            if m.name is None:
                continue
            if old is not None and m.name != old:
                if m.score < m.scores.get(old, -2.0) + self.config.reclassify_margin:
                    continue
            if m.name == old:
                self.track_class[tid] = (old, m.score)
                continue
            self.track_class[tid] = (m.name, m.score)
            self._set_class(tid, m.name)
            proto = kd.classes.get(m.name)
            specific = m.name if proto.kind == kd_store.ClassKind.SPECIFIC else None
            kd.update_entity(tid, generic_classes=m.generic, specific_class=specific)
            if old is not None and confirmed:
                events.append(emit(kd, EventClass.RECLASSIFIED, t_ns, [tid], 4, _unit(m.score)))
            if (
                confirmed
                and self.config.found_specific
                and m.score < self.config.classify.match
                and specific is None
            ):
                kd.found_specific_class(tid)
                self.classifier.refresh()
                self.class_names = [p.name for p in kd.classes]
                self._class_index = {n: i for i, n in enumerate(self.class_names)}
        return events

    def _set_class(self, entity_id: int, name: str | None) -> None:
        """Point ``entity_id``'s pixels in the class images at class ``name``."""
        self.class_table.set([entity_id], [self._class_index.get(name, -1) if name else -1])

    def _observe_appearance(self, table: dict[int, float], tid: int, value: float) -> None:
        """Running mean (exponential, ``appearance_gain``) of an object's observed appearance
        (LADAR intensity or camera grey), for classification."""
        if not math.isfinite(value):
            return
        old = table.get(tid)
        table[tid] = value if old is None else old + self.config.appearance_gain * (value - old)

    def _observe_shape(self, tid: int, a: SegmentAttributes, s: int) -> None:
        """Running mean (``appearance_gain``) of the shape of object ``tid``'s points in this
        sweep's segment ``s`` (:data:`SHAPE_KEYS`), and the longest extent it was seen with.
        The scatter's thickness and curvature say nothing of a segment whose points lie on a
        line (one scan row, or a few returns: its smallest two eigenvalues are both noise), so
        those are averaged over the sweeps that saw a surface (``SHAPE_MIN_BREADTH_M`` spread
        along the middle axis and ``SHAPE_MIN_PIXELS`` returns) only."""
        v = np.array([float(getattr(a, k)[s]) for k in SHAPE_KEYS[:-1]] + [float(a.length_m[s])])
        if not np.all(np.isfinite(v)):
            return
        surface = a.breadth_m[s] >= SHAPE_MIN_BREADTH_M and a.n_pixels[s] >= SHAPE_MIN_PIXELS
        old = self.track_shape.get(tid)
        if old is None:
            old = np.full(len(SHAPE_KEYS), np.nan)
        new = np.where(np.isnan(old), v, old + self.config.appearance_gain * (v - old))
        if not surface:
            new[:_SURFACE_KEYS] = old[:_SURFACE_KEYS]
        new[-1] = np.fmax(old[-1], v[-1])
        self.track_shape[tid] = new

    def _shape_of(self, tid: int) -> dict[str, float]:
        """The shape attributes object ``tid`` has been observed with (none if never)."""
        v = self.track_shape.get(tid)
        if v is None:
            return {}
        return {k: float(x) for k, x in zip(SHAPE_KEYS, v, strict=True) if np.isfinite(x)}

    def _appearance_of(self, tid: int) -> dict[str, float]:
        """The appearance attributes object ``tid`` has been observed with: ``reflectance``
        (mean LADAR intensity over ``intensity_per_reflectance``, when that is known) and
        ``camera_intensity``
        (mean grey 0..1 of its returns in the camera image). An attribute never observed is
        left out, so the classifier ignores it rather than reading it as zero."""
        cfg = self.config
        if not cfg.appearance_classes:
            return {}
        out = {}
        if tid in self.track_reflectance and cfg.intensity_per_reflectance:
            out["reflectance"] = self.track_reflectance[tid] / cfg.intensity_per_reflectance
        if tid in self.track_camera:
            out["camera_intensity"] = self.track_camera[tid]
        return out

    def _class_images(
        self, entity_images: dict[int, np.ndarray], flat: np.ndarray
    ) -> tuple[Mapping[int, np.ndarray], Mapping[str, np.ndarray], np.ndarray]:
        """Class images per level and value images of the level-4/3 composite, made when
        first asked for from this cycle's classes (a copy of the class table), and the class
        of each valid pixel ``flat`` in the composite (its object's, else its surface's)."""
        lut = self.class_table.lut.copy()
        classes = LazyImages(entity_images, lambda k: class_image(lut, entity_images[k]))

        def composite() -> np.ndarray:
            c4 = classes[4]
            return np.where(c4 >= 0, c4, classes[3])

        tables = self._value_tables()
        values = LazyImages(tables, lambda n: value_images(composite(), {n: tables[n]})[n])
        c4 = class_image(lut, entity_images[4].reshape(-1)[flat])
        c3 = class_image(lut, entity_images[3].reshape(-1)[flat])
        return classes, values, np.where(c4 >= 0, c4, c3)

    def _value_tables(self) -> dict[str, np.ndarray]:
        """Value of every class of ``class_names`` (cached until a class is founded)."""
        if self._values[0] != len(self.class_names):
            self._values = (len(self.class_names), class_values(self.kd.classes, self.class_names))
        return self._values[1]

    def _confirmed_pixels(self, image4: np.ndarray) -> np.ndarray:
        """(H, W) bool pixels of confirmed objects (one gather through a table by id)."""
        tr = self.tracker.tracks
        ids = tr.id[(tr.status == TrackStatus.CONFIRMED) & (tr.id >= 0)]
        if ids.size == 0:
            return np.zeros(image4.shape, dtype=bool)
        lut = np.zeros(max(int(ids.max()), int(image4.max(initial=0))) + 1, dtype=bool)
        lut[ids] = True
        return lut[np.maximum(image4, 0)] & (image4 >= 0)

    # ------------------------------------------------------------------ level 3 and 2

    def _ground_entity(
        self, t_ns: int, xyz_w: np.ndarray, ground: np.ndarray, T_world_ladar: np.ndarray
    ) -> int:
        """The ground's level-3 entity, its plane fitted to the ground pixels ``ground`` (H, W)
        of ``xyz_w`` (H, W, 3) world points within 20 m of the sensor (:func:`ground_plane`)."""
        kd = self.kd
        if self.ground_id is None:
            self.ground_id = kd.add_entity(
                "ground",
                Level.SURFACE,
                generic_classes=("ground",) if "ground" in kd.classes else (),
                images=(IMAGE_NAMES[3],),
                status=Status.CONFIRMED,
                confidence=1.0,
            ).id
            self._set_class(self.ground_id, "ground")
        gid = self.ground_id
        fit = ground_plane(xyz_w, ground, T_world_ladar[:3, 3], 20.0)
        if fit is not None:
            coef, rough, n_near = fit
            slope = float(math.atan(math.hypot(coef[0], coef[1])))
            z0 = float(T_world_ladar[2, 3] + coef[2])  # the plane under the sensor
            kd.update_entity(
                gid,
                attributes={
                    "slope_rad": Attribute(observed=slope, observed_var=0.01),
                    "roughness_m": Attribute(observed=rough, observed_var=0.0001),
                    "n_pixels": Attribute(observed=float(n_near)),
                },
            )
            last = kd.get(gid).state
            if last is None or last.t_ns < t_ns:
                pos = (T_world_ladar[0, 3], T_world_ladar[1, 3], z0)
                kd.observe(gid, kd_store.State(t_ns, "world", pos))
        return gid

    def _surfaces(
        self,
        t_ns: int,
        image3: np.ndarray,
        labels: np.ndarray,
        a: SegmentAttributes,
        obj_ids: np.ndarray,
        ground: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Level 3 beyond the ground: the vertical planar face of a confirmed object (a wall, a
        building side) is a surface entity, part of that object, classified among the level's
        prototypes (slope, roughness, height); where it meets the ground, the pixels of the
        face just above a ground pixel are its contact boundary (a level-2 list lying on the
        ground). Returns (image3 with the faces, (H, W) int64 contact-boundary ids, -1 none)."""
        kd = self.kd
        tr = self.tracker.tracks
        confirmed = set(tr.id[tr.status == TrackStatus.CONFIRMED].tolist())
        face_of = np.full(len(a) + 1, -1, dtype=np.int64)  # per segment (last: no segment)
        contact_of = face_of.copy()
        for s in np.flatnonzero(vertical_face(a, self.config)):
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
            m = self._surface_classifier.classify(attrs)
            kd.update_entity(
                int(face_of[s]),
                attributes={k: Attribute(observed=v) for k, v in attrs.items()},
                generic_classes=m.generic,
            )
            self._set_class(int(face_of[s]), m.name)
        face = face_of[labels]  # labels -1 picks the last entry: no face
        image3 = np.where(face >= 0, face, image3)
        above_ground = np.zeros_like(ground)
        above_ground[:-1] = ground[1:]
        contact = np.where((face >= 0) & above_ground, contact_of[labels], -1)
        return image3, contact

    def _surface_of(self, oid: int, t_ns: int) -> tuple[int, int]:
        """(surface id, contact boundary id) of object ``oid``'s face, made on first sight."""
        if oid not in self.track_surface:
            kd = self.kd
            sid = kd.add_entity(
                f"face of {oid}",
                Level.SURFACE,
                images=(IMAGE_NAMES[3],),
                status=Status.CONFIRMED,
                confidence=1.0,
            ).id
            kd.relate(sid, "belongs_to", oid, t_ns=t_ns)
            bid = kd.add_entity(
                f"contact of {sid}",
                Level.LIST,
                generic_classes=("slope_edge",) if "slope_edge" in kd.classes else (),
                images=(IMAGE_NAMES[2],),
                status=Status.CONFIRMED,
                confidence=1.0,
            ).id
            kd.relate(bid, "belongs_to", sid, t_ns=t_ns)
            if self.ground_id is not None:
                kd.relate(bid, "on_top_of", self.ground_id, t_ns=t_ns)
            self._set_class(bid, "slope_edge")
            self.track_surface[oid] = (sid, bid)
        return self.track_surface[oid]

    def _free_surfaces(
        self,
        t_ns: int,
        image3: np.ndarray,
        contact: np.ndarray,
        xyz_g: np.ndarray,
        free: np.ndarray,
        ground: np.ndarray,
        T_world_ladar: np.ndarray,
        row_el: np.ndarray,
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
        ``contact``, as are the creases). Returns (image3 with the surfaces, their ids)."""
        cfg = self.config
        kd = self.kd
        H, W = free.shape
        tracker = self.surface_tracker
        for sid in tracker.forget(t_ns):
            self._surface_gone(int(sid))
        self._forget_creases(t_ns)
        grid = patch_grid(xyz_g, free, cfg.list_config)
        obs = group_patches(grid, 2 * math.pi / W, _row_step(row_el), cfg.surfaces)
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
                kd.add_entity(
                    f"surface@{t_ns}",
                    Level.SURFACE,
                    images=(IMAGE_NAMES[3],),
                    status=Status.HYPOTHESIZED,
                    confidence=0.3,
                ).id
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
        matches = self._surface_classifier.classify_many(rows)
        self.class_table.set(ids, [self._class_index.get(m.name or "", -1) for m in matches])
        was = self._surface_status.get
        changed = np.array([was(int(i)) != int(st) for i, st in zip(ids, status, strict=True)])
        due = self._due(ids) | (index < 0) | changed
        for k in np.flatnonzero(due & ~denied):
            sid = int(ids[k])
            self._surface_status[sid] = int(status[k])
            kd.update_entity(
                sid,
                attributes={n: Attribute(observed=v) for n, v in rows[k].items()},
                generic_classes=matches[k].generic,
                status=_STATUS[TrackStatus(int(status[k]))],
                confidence=_unit(conf[k]),
            )
            last = kd.get(sid).state
            if last is None or last.t_ns < t_ns:
                kd.observe(sid, kd_store.State(t_ns, "world", c_w[k]))
        # a denied grouping hypothesis releases its pixels
        for sid in tracker.drop_denied():
            self._surface_gone(int(sid), Status.DENIED)
        keep = ~denied[lab]
        px, row, lab = px[keep], row[keep], lab[keep]
        self._free_px.reshape(-1)[px] = True
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
            self.config.surfaces, az_step_rad=2 * math.pi / W,
        )  # fmt: skip
        if len(cr):
            pairs = zip(ent[cr.a].tolist(), ent[cr.b].tolist(), strict=True)
            crease_ids = np.array([self._crease_of(a, b, t_ns) for a, b in pairs], np.int64)
            contact.reshape(-1)[cr.pixel] = crease_ids[cr.crease]

    def _forget_creases(self, t_ns: int) -> None:
        """Creases unseen for ``forget_s`` are gone."""
        forget_ns = self.config.surfaces.forget_s * 1e9
        for key, (lid, seen_ns) in list(self._crease.items()):
            if t_ns - seen_ns > forget_ns:
                self.kd.update_entity(lid, status=Status.GONE)
                del self._crease[key]

    def _crease_of(self, sid_a: int, sid_b: int, t_ns: int) -> int:
        """The crease list between surfaces ``sid_a`` and ``sid_b``, made on first sight: a
        slope edge belonging to ``sid_a`` and beside ``sid_b`` (the KD's belongs_to is a tree:
        one parent), its name naming both."""
        key = (min(sid_a, sid_b), max(sid_a, sid_b))
        if key not in self._crease:
            kd = self.kd
            lid = kd.add_entity(
                f"crease of {key[0]} and {key[1]}",
                Level.LIST,
                generic_classes=("slope_edge",) if "slope_edge" in kd.classes else (),
                images=(IMAGE_NAMES[2],),
                status=Status.CONFIRMED,
                confidence=1.0,
            ).id
            kd.relate(lid, "belongs_to", sid_a, t_ns=t_ns)
            kd.relate(lid, "beside", sid_b, t_ns=t_ns)
            self._set_class(lid, "slope_edge")
            self._crease[key] = (lid, t_ns)
        lid = self._crease[key][0]
        self._crease[key] = (lid, t_ns)
        return lid

    def _due(self, ids: np.ndarray) -> np.ndarray:
        """(n,) bool: frames rewritten this sweep. List and surface frames are rewritten in
        turn, each every ``kd_refresh_sweeps`` sweeps (the pipeline's tables and images hold
        the latest), so the KD writes per sweep stay a fixed share of the entities."""
        return (ids % self.config.kd_refresh_sweeps) == (
            self._sweep % self.config.kd_refresh_sweeps
        )

    def _contact_of(self, sid: int, t_ns: int) -> int:
        """The contact boundary list of free surface ``sid`` with the ground, made on first
        sight: it belongs to the surface and lies on the ground."""
        if sid not in self._surface_contact:
            kd = self.kd
            bid = kd.add_entity(
                f"contact of {sid}",
                Level.LIST,
                generic_classes=("slope_edge",) if "slope_edge" in kd.classes else (),
                images=(IMAGE_NAMES[2],),
                status=Status.CONFIRMED,
                confidence=1.0,
            ).id
            kd.relate(bid, "belongs_to", sid, t_ns=t_ns)
            if self.ground_id is not None:
                kd.relate(bid, "on_top_of", self.ground_id, t_ns=t_ns)
            self._surface_contact[sid] = bid
            self._set_class(bid, "slope_edge")
        return self._surface_contact[sid]

    def _surface_gone(self, sid: int, status: Status = Status.GONE) -> None:
        """A free surface unseen for ``forget_s`` (or denied, ``status``): it and its lists
        are gone."""
        self.kd.update_entity(sid, status=status)
        self._surface_status.pop(sid, None)
        parts = self._lists_of.pop(sid, [])
        if sid in self._surface_contact:
            parts.append(self._surface_contact.pop(sid))
        self._parts_gone(parts)

    def _parts_gone(self, parts) -> None:
        """Lists (or contacts) whose owner went go too; a denied list the KD has already
        dropped stays dropped."""
        for lid in parts:
            if lid in self.kd and self.kd.get(lid).status != Status.DENIED:
                self.kd.update_entity(lid, status=Status.GONE)

    def _lists(
        self,
        t_ns: int,
        owner: np.ndarray,
        rng: np.ndarray,  # (H, W) range m, inf where empty
        valid: np.ndarray,
        intensity: np.ndarray,
    ) -> np.ndarray:
        """Level 2: list entities on the pixels of ``owner`` ((H, W) int64 id of the confirmed
        object, else the level-3 surface, each pixel is on; -1 none). Range edges, brightness
        edges (:func:`brightness_edges`, off the range edges), vertices (edge ends and
        junctions, :func:`edge_branches`) and the surface patches of the free surfaces.

        One list entity per (owner, kind), made on first sight and kept while its owner
        lives: "the range edges of object 12" rather than one frame per edge piece per sweep.
        Edge pieces split and join from sweep to sweep as the view changes, so frames of
        single pieces would be born and die every cycle with nothing to track; per (owner,
        kind) the frames are bounded by four per owner, persist as long as their owner, and
        their attributes (integrated over all the pixels of that kind on the owner) are
        stable enough to filter and classify. The individual pieces stay visible in the
        level-2 image. Returns the (H, W) int64 level-2 entity image."""
        cfg = self.config
        kd = self.kd
        r_edge = range_edges(rng, valid, cfg.segments)
        inten_mean = mean_intensity(intensity, valid)
        b_edge = brightness_edges(intensity, valid, cfg.list_config, inten_mean) & ~r_edge
        patch = self._free_px if self._free_px.shape == owner.shape else np.zeros_like(valid)
        # each pixel's list, its branches and the lists' sums, in one compiled pass
        slots, out, branches, missing, sums = list_slots_and_sums(
            owner, r_edge, b_edge, patch, self._list_lut, self._list_ids, rng, intensity
        )
        first_new = self._list_ids.size
        if missing.size:
            if int(missing.max()) >= self._list_lut.size:
                grown = np.full(max(int(missing.max()) + 1, 2 * self._list_lut.size), -1, np.int64)
                grown[: self._list_lut.size] = self._list_lut
                self._list_lut = grown
            new = []
            for k in missing:
                oid, kd_kind = divmod(int(k), len(ListKind))
                lid = kd.add_entity(
                    f"{KIND_CLASS[ListKind(kd_kind)]} of {oid}",
                    Level.LIST,
                    images=(IMAGE_NAMES[2],),
                    status=Status.HYPOTHESIZED,
                    confidence=self.config.tracker.confidence0,
                ).id
                kd.relate(lid, "belongs_to", oid, t_ns=t_ns)
                self._list_lut[k] = first_new + len(new)
                self._lists_of.setdefault(oid, []).append(lid)
                new.append(lid)
            self._list_ids = np.r_[self._list_ids, np.array(new, dtype=np.int64)]
            self._list_conf = np.r_[
                self._list_conf, np.full(len(new), self.config.tracker.confidence0)
            ]
            self._list_hits = np.r_[self._list_hits, np.zeros(len(new), dtype=np.int64)]
            self._list_open = np.r_[self._list_open, np.ones(len(new), dtype=bool)]
            self._list_key = np.r_[self._list_key, missing.astype(np.int64)]
            self._list_dead = np.r_[self._list_dead, np.zeros(len(new), dtype=bool)]
            fill_slots(slots, out, self._list_lut, self._list_ids)
        if self._list_ids.size == 0:
            return np.full(owner.shape, -1, dtype=np.int64)
        if missing.size:  # new lists: sum again with their pixels
            sums = list_sums(slots, rng, intensity, r_edge | b_edge, branches, self._list_ids.size)
        # attributes of every list seen; classes and frames of those due this sweep and new
        a = list_attributes(sums, 2 * math.pi / owner.shape[1], inten_mean)
        self._list_confidence(a.ids)
        # a hypothesis the KD's short-term memory has let go of is treated as denied
        gone = np.array([int(i) not in kd for i in self._list_ids[a.ids]], dtype=bool)
        if gone.any():
            self._release_lists(a.ids[gone])
        ids = self._list_ids[a.ids]
        due = (self._due(ids) | (a.ids >= first_new)) & ~self._list_dead[a.ids]
        rows = [r for r, d in zip(a.as_dicts(), due, strict=True) if d]
        matches = self._list_classifier.classify_many(rows)
        ids, conf = ids[due], self._list_conf[a.ids[due]]
        self.class_table.set(ids, [self._class_index.get(m.name or "", -1) for m in matches])
        for i, c, r, m in zip(ids, conf, rows, matches, strict=True):
            kd.update_entity(
                int(i),
                attributes={n: Attribute(observed=v) for n, v in r.items()},
                generic_classes=m.generic,
                confidence=_unit(c),
            )
        return out

    def _list_confidence(self, seen_slots: np.ndarray) -> None:
        """Recursive confidence of every list (4.5.3, as for objects and groups): each sweep
        a list has pixels it rises by the tracker's gain ``alpha`` towards 1, each sweep it
        has none it decays by the same gain. A hypothesized list is confirmed above the
        tracker's ``confirm`` after ``min_hits`` sweeps and denied below its ``deny`` (a
        few pixels of one sweep that never came back); confirmed lists go with their owner."""
        tc = self.config.tracker
        seen = np.zeros(self._list_ids.size, dtype=bool)
        seen[seen_slots] = True
        c = self._list_conf
        c[seen] += tc.alpha * (1.0 - c[seen])
        c[~seen] *= 1.0 - tc.alpha
        self._list_hits[seen] += 1
        confirm = self._list_open & (c >= tc.confirm) & (self._list_hits >= tc.min_hits)
        deny = self._list_open & (c < tc.deny) & (self._list_hits > 0) & ~seen
        for k, status in ((confirm, Status.CONFIRMED), (deny, Status.DENIED)):
            for slot in np.flatnonzero(k):
                lid = int(self._list_ids[slot])
                if lid in self.kd and self.kd.get(lid).status == Status.HYPOTHESIZED:
                    self.kd.update_entity(lid, status=status, confidence=_unit(c[slot]))
        self._list_open &= ~(confirm | deny)
        self._release_lists(np.flatnonzero(deny))

    def _release_lists(self, slots: np.ndarray) -> None:
        """Denied (or forgotten) lists: their (owner, kind) starts a new hypothesis if its
        pixels come back, and they are no longer their owner's."""
        for slot in slots:
            key = int(self._list_key[slot])
            if 0 <= key < self._list_lut.size and self._list_lut[key] == slot:
                self._list_lut[key] = -1
            owned = self._lists_of.get(key // len(ListKind), [])
            if int(self._list_ids[slot]) in owned:
                owned.remove(int(self._list_ids[slot]))
        self._list_dead[slots] = True
        self._list_open[slots] = False

    # ------------------------------------------------------------------ level 5

    def _groups(self, t_ns: int, image4: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """Level 5: groups of confirmed objects (:func:`group_labels`). Only objects whose
        motion the filter is sure of (:func:`evident_speed`) and whose class moves (vehicle,
        person) link as moving, so static clutter with noisy velocities makes no convoy or
        crowd. A group starts hypothesized and is confirmed by its own recursive confidence
        as it persists (:meth:`_group_confidence`), like any other entity."""
        kd = self.kd
        tr = self.tracker.tracks
        conf = np.flatnonzero(tr.status == TrackStatus.CONFIRMED)
        ids = tr.id[conf]
        cls = [self.track_class.get(int(i), (None, 0))[0] for i in ids]
        is_tree = np.array([c == "tree" for c in cls], dtype=bool)
        mobile = np.array([c in MOBILE_CLASSES for c in cls], dtype=bool)
        tc = self.config.tracker
        sure = tr.moving(tc)[conf] & (evident_speed(tr.x[conf], tr.P[conf], tc.evident_sigmas) > 0)
        v = np.where((mobile & sure)[:, None], tr.x[conf, 3:5], 0.0)
        lab = group_labels(tr.x[conf, :2], v, is_tree, self.config.groups)
        current = [
            frozenset(int(i) for i in ids[lab == g]) for g in range(int(lab.max(initial=-1)) + 1)
        ]
        carried, _, ended = match_groups(self.groups, current)
        events: list[int] = []
        groups: dict[int, frozenset[int]] = {}
        for i, members in enumerate(current):
            if i in carried:
                gid = carried[i]
            else:
                gid = kd.add_entity(
                    f"group@{t_ns}",
                    Level.GROUP,
                    images=(IMAGE_NAMES[5],),
                    status=Status.HYPOTHESIZED,
                    confidence=self.config.tracker.confidence0,
                ).id
            self._group_confidence(gid, t_ns, members, events)
            old = self.groups.get(gid, frozenset())
            for m in members - old:
                kd.relate(m, "belongs_to", gid, t_ns=t_ns)
            for m in old - members:
                if m in kd:
                    kd.unrelate(m, "belongs_to", gid, t_ns=t_ns)
            groups[gid] = members
            self._group_state(gid, members, t_ns)
        # a previous group whose members now lie in two or more groups has split
        for gid, old in self.groups.items():
            into = [g for g, m in groups.items() if m & old]
            if len(into) >= 2:
                events.append(emit(kd, EventClass.GROUP_SPLIT, t_ns, [gid, *into], 5))
        for gid in ended:
            for m in self.groups[gid]:
                if m in kd:
                    kd.unrelate(m, "belongs_to", gid, t_ns=t_ns)
            was_confirmed = kd.get(gid).status == Status.CONFIRMED
            kd.update_entity(gid, status=Status.GONE if was_confirmed else Status.DENIED)
            if was_confirmed:
                events.append(emit(kd, EventClass.VANISHED, t_ns, [gid], 5))
        self.groups = groups
        image5 = np.full(image4.shape, -1, dtype=np.int64)
        for gid, members in groups.items():
            image5[np.isin(image4, np.fromiter(members, np.int64))] = gid
        return image5, events

    def _group_confidence(
        self, gid: int, t_ns: int, members: frozenset[int], events: list[int]
    ) -> None:
        """Recursive confidence of group ``gid`` seen again this cycle: it rises by the
        tracker's gain ``alpha`` towards 1 each cycle the group persists; the group is
        confirmed (and "group_formed" emitted) once it is above the tracker's ``confirm``
        after ``min_hits`` cycles, as an object track is."""
        tc = self.config.tracker
        f = self.kd.get(gid)
        c = f.confidence + tc.alpha * (1.0 - f.confidence) if gid in self.groups else f.confidence
        hits = self._group_hits.get(gid, 0) + 1
        self._group_hits[gid] = hits
        changes: dict[str, object] = {"confidence": _unit(c)}
        if f.status == Status.HYPOTHESIZED and c >= tc.confirm and hits >= tc.min_hits:
            changes["status"] = Status.CONFIRMED
            events.append(emit(self.kd, EventClass.GROUP_FORMED, t_ns, [gid, *members], 5))
        self.kd.update_entity(gid, **changes)

    def _group_state(self, gid: int, members: frozenset[int], t_ns: int) -> None:
        tr = self.tracker.tracks
        k = np.isin(tr.id, np.fromiter(members, np.int64))
        p, v = tr.x[k, :3], tr.x[k, 3:]
        extent = float(np.ptp(p[:, :2], axis=0).max()) if p.shape[0] > 1 else 0.0
        spread = max(extent, 1.0)
        speed = float(np.hypot(*v[:, :2].mean(axis=0)))
        attrs = {
            "count": Attribute(observed=float(k.sum())),
            "length_m": Attribute(observed=extent),
            "speed_mps": Attribute(observed=speed),
            "density_per_m2": Attribute(observed=float(k.sum()) / (spread * spread)),
        }
        m = Classifier(self.kd.classes, Level.GROUP).classify(
            {n: a.observed for n, a in attrs.items()}
        )
        self.kd.update_entity(gid, attributes=attrs, generic_classes=m.generic)
        self._set_class(gid, m.name)
        last = self.kd.get(gid).state
        t = max(t_ns, last.t_ns + 1) if last is not None else t_ns
        self.kd.observe(gid, kd_store.State(t, "world", p.mean(axis=0), velocity_xyz=v.mean(0)))


def column_poses(
    img: EgosphereImage,
    t_ns: int,
    T_world_prev: np.ndarray,
    t_prev_ns: int,
    T_world_ladar: np.ndarray,
    pose_t_ns: int,
) -> np.ndarray:
    """(W, 4, 4) sensor pose at each column's firing time (the mean time of its returns,
    ``t_ns`` + offset), at constant velocity through the two poses (slerp, extrapolated past
    ``pose_t_ns`` when the column fired later)."""
    v = img.valid_first
    off = np.where(v, img.t_offset_ns[..., 0], 0).sum(axis=0, dtype=np.float64)
    mid = off / np.maximum(v.sum(axis=0), 1)
    alpha = (t_ns + mid - t_prev_ns) / float(pose_t_ns - t_prev_ns)
    return interpolate_pose(T_world_prev, T_world_ladar, alpha.astype(np.float64))


def vertical_face(a: SegmentAttributes, cfg: SPConfig) -> np.ndarray:
    """(K,) bool: segments that are a broad, thin plane within ``face_tilt_deg`` of vertical
    (a wall or a building side: a level-3 surface, reference 001, 4.5.6)."""
    upright = a.verticality <= math.sin(math.radians(cfg.face_tilt_deg))
    return upright & (a.breadth_m >= cfg.face_breadth_m) & (a.thickness_m <= cfg.face_thick_m)


def terrain_patch(a: SegmentAttributes, cfg: SPConfig) -> np.ndarray:
    """(K,) bool: segments that are a broad, thin plane tilted less than ``terrain_tilt_deg``,
    lower than ``terrain_max_height_m`` (a roof is higher) and starting within
    ``terrain_clearance_m`` of the ground under it (a car's hood does not): level 3 surfaces
    of the ground (reference 001, 4.5.6), not objects standing on it."""
    flat = a.verticality >= math.cos(math.radians(cfg.terrain_tilt_deg))
    plane = (a.breadth_m >= cfg.terrain_breadth_m) & (a.thickness_m <= cfg.terrain_thick_m)
    low = (a.height_m < cfg.terrain_max_height_m) & (a.clearance_m <= cfg.terrain_clearance_m)
    return flat & plane & low


def status_code(s: Status) -> int:
    return {
        Status.HYPOTHESIZED: TrackStatus.HYPOTHESIZED,
        Status.CONFIRMED: TrackStatus.CONFIRMED,
        Status.DENIED: TrackStatus.DENIED,
        Status.GONE: TrackStatus.GONE,
    }[s]


def _unit(x: float) -> float:
    return float(min(max(x, 0.0), 1.0))


def _with_min(cfg: SegmentConfig, min_pixels: int) -> SegmentConfig:
    return dataclasses.replace(cfg, min_pixels=min_pixels)


def _drop_small(
    labels: np.ndarray, attention: np.ndarray, n_min: int, n_min_att: int
) -> np.ndarray:
    """Keep segments of at least ``n_min`` pixels, or ``n_min_att`` when inside a window;
    renumber 0..K-1."""
    flat = labels.reshape(-1)
    has = flat >= 0
    if not has.any():
        return labels
    K = int(flat.max()) + 1
    n = np.bincount(flat[has], minlength=K)
    att = np.bincount(flat[has], weights=attention.reshape(-1)[has], minlength=K) > 0
    keep = (n >= n_min) | (att & (n >= n_min_att))
    new = np.full(K, -1, dtype=np.int64)
    new[keep] = np.arange(int(keep.sum()))
    out = np.full_like(flat, -1)
    out[has] = new[flat[has]]
    return out.reshape(labels.shape)


def _attributes(
    a: SegmentAttributes, s: int, w: np.ndarray, Pw: np.ndarray, x: np.ndarray
) -> dict[str, Attribute]:
    """Observed (this segment) and estimated (the what-filter) attributes of one object."""
    obs = {
        "length_m": float(a.length_m[s]),
        "width_m": float(a.width_m[s]),
        "height_m": float(a.height_m[s]),
    }
    est = {"length_m": (w[0], Pw[0]), "width_m": (w[1], Pw[1]), "height_m": (w[2], Pw[2])}
    out = {
        k: Attribute(
            observed=v,
            observed_var=0.25,
            estimated=float(est[k][0]),
            estimated_var=float(est[k][1]),
        )
        for k, v in obs.items()
    }
    out["speed_mps"] = Attribute(estimated=float(np.hypot(x[3], x[4])))
    out["area_m2"] = Attribute(observed=float(a.area_m2[s]))
    out["volume_m3"] = Attribute(observed=float(a.volume_m3[s]))
    out["intensity"] = Attribute(observed=float(a.intensity[s]))
    out["curvature"] = Attribute(observed=float(a.curvature[s]))
    out["n_pixels"] = Attribute(observed=float(a.n_pixels[s]))
    return out

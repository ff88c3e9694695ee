"""SP level 4: objects, tracked from sweep to sweep.

Reference 001, 4.5.6 (level 4: objects grouped from surfaces and segments), 4.5.1 (the five
SP functions), 4.5.3 (hypothesize and test: M-of-N birth, confirm, deny), 4.5.4 (recursive
estimation: Kalman filters). The five functions are the methods of :class:`ObjectLevel`:

- :meth:`~ObjectLevel.window`: the tracks' predicted positions, WM's surprise points, last
  sweep's new and provisional hypotheses (:func:`window_mask`);
- :meth:`~ObjectLevel.group`: contiguity and range steps (:func:`label_objects`);
- :meth:`~ObjectLevel.compute`: segment attributes (:func:`segment_attributes`), grazing and
  collinear pieces merged, people cut apart, low and terrain-like segments back to ground;
- :meth:`~ObjectLevel.filter`: association, Kalman updates, confirm / deny (:class:`Tracker`);
- :meth:`~ObjectLevel.classify`: against the level-4 prototypes (:class:`Classifier`).

The objects' frames, states and events are observations (:mod:`sp.observations`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from core.geometry import matrix_to_quat, rot_z
from kd_store import Attribute, ClassKind, Level, StateBatch, Status
from logs.types import CameraFrame
from sp.appearance import object_appearance
from sp.classify import Classifier
from sp.computation import (
    SegmentAttributes,
    ground_below,
    segment_attributes,
    segment_roughness,
)
from sp.context import IMAGE_NAMES, KD_STATUS, SPContext, row_step, unit
from sp.egosphere import EgosphereImage
from sp.events import EventClass
from sp.level3_surfaces import GroundPixels, foot_rise_deg, terrain_patch
from sp.observations import AppearanceObserved, ClassFounded, FrameChange, StatesObserved
from sp.reid import Lost, LostObjects
from sp.scene_prior import ScenePrior
from sp.segments import (
    SegmentConfig,
    label_objects,
    merge_behind_occluders,
    merge_collinear,
    merge_grazing,
    split_at_gap,
    split_by_predictions,
)
from sp.tracking import Measurements, Tracker, Tracks, TrackStatus
from sp.windowing import window_mask

# shape attributes of an object's points, observed per sweep (sp.computation.SegmentAttributes,
# same names) and averaged per object; the last, ``longest_m``, is the longest extent the object
# was seen with (it grows as more of a wall comes into view)
SHAPE_KEYS = ("thickness_m", "curvature", "verticality", "breadth_m", "clearance_m", "longest_m")
_SURFACE_KEYS = 3  # the first three describe a surface of points, not a line (_observe_shape)
SHAPE_MIN_BREADTH_M = 0.05  # a segment's points spread this far along its middle axis ...
SHAPE_MIN_PIXELS = 12  # ... in this many returns at least, or its thickness is unknown


def count_in(labels: np.ndarray, mask: np.ndarray, k: int) -> np.ndarray:
    """(k,) int64: how many pixels of each of the k segments of ``labels`` (H, W) int64 (-1
    none) lie in ``mask`` (H, W) bool."""
    return np.bincount(labels[mask & (labels >= 0)], minlength=k)[:k]


@dataclass
class Segments:
    """Level 4's grouping and computation of one sweep.

    labels:      (H, W) int64 segment index per pixel, -1 none.
    attributes:  per segment (K of them) attributes, world frame.
    ground:      (H, W) bool ground pixels, with the low and terrain-like segments added.
    roughness_m: (K,) float64 texture of each segment's returns (NaN unknown), m
                 (:func:`sp.computation.segment_roughness`).
    """

    labels: np.ndarray
    attributes: SegmentAttributes
    ground: np.ndarray
    roughness_m: np.ndarray


@dataclass
class ObjectsObserved:
    """Level 4's filtering of one sweep.

    ids:       (K,) int64 object frame id per segment, -1 none (not framed yet, or unmatched).
    events:    ids of the events observed (appeared, confirmed, denied, vanished).
    finished:  (F,) int64 ids of the tracks that ended this sweep (their parts go with them;
               negative ids never had a frame).
    """

    ids: np.ndarray
    events: list[int]
    finished: np.ndarray


@dataclass
class ClassEvidence:
    """What one track's class rests on, so that a class taken on good views is not given up
    on poorer ones (reference 001, 4.5.3: a hypothesis stands until the evidence against it
    is as good as the evidence for it). A car, a wall or a tree seen well while the vehicle
    passed and then only by a few returns as it is left behind (far, at a grazing angle, its
    visible part sliding along it) is not renamed by those last views; the KD keeps one class
    per entity, so a late wrong one is wrong for every state it holds.

    support: class name -> most returns of a view in which that class was the track's.
    best:    the class that scored highest in the latest measured views, ``run`` of them in a
             row; ``held``: the measured views the present class scored highest in since it
             was taken.
    """

    support: dict[str, int] = dataclasses.field(default_factory=dict)
    best: str | None = None
    run: int = 0
    held: int = 0

    def observe(self, best: str, present: str | None, n_returns: int) -> None:
        """A view of ``n_returns`` (> 0) returns in which class ``best`` scored highest while
        the track's class was ``present``."""
        self.run = self.run + 1 if best == self.best else 1
        self.best = best
        if best == present:
            self.held += 1
            self.support[best] = max(self.support.get(best, 0), n_returns)

    def may_change(self, present: str, new: str, n_returns: int, min_share: float) -> bool:
        """Whether the class may change from ``present`` to ``new`` on a view of
        ``n_returns`` returns: the view, or one in which the track was a ``new`` already, has
        at least ``min_share`` of the returns of the best view that was a ``present``; or
        ``new`` has scored highest in more measured views in a row than ``present`` did
        since it was taken (a tall tree seen near is cut by the sensor's field of view and
        looks like a building, but from farther out a tree for longer)."""
        seen = max(n_returns, self.support.get(new, 0))
        return seen >= min_share * self.support.get(present, 0) or self.run > self.held

    def take(self, new: str, n_returns: int) -> None:
        """The class is now ``new``, taken on a view of ``n_returns`` returns."""
        self.support[new] = max(self.support.get(new, 0), n_returns)
        self.held = 0


class ObjectLevel:
    """Level-4 objects: the tracker and, per object id, its class (name, score), running
    appearance (LADAR intensity, camera grey) and shape (:data:`SHAPE_KEYS`)."""

    def __init__(self, ctx: SPContext) -> None:
        self.ctx = ctx
        self.tracker = Tracker(ctx.config.tracker)
        self.classifier = Classifier(ctx.classes, Level.OBJECT, ctx.config.classify)
        self.scene_prior: ScenePrior | None = None  # made for the classifier's discriminant
        self.track_class: dict[int, tuple[str | None, float]] = {}
        self.track_reflectance: dict[int, float] = {}  # object id -> mean LADAR intensity
        self.track_camera: dict[int, float] = {}  # object id -> mean camera grey (0..1)
        self.track_excess_green: dict[int, float] = {}  # object id -> mean excess green (-1..2)
        self.track_shape: dict[int, np.ndarray] = {}  # object id -> running shape (SHAPE_KEYS)
        self.track_roughness: dict[int, float] = {}  # object id -> mean texture, m
        self.attention = np.zeros((0, 0), dtype=bool)  # last sweep's unexplained pixels
        self._sensor_xy: np.ndarray | None = None  # the sensor's world xy this sweep
        self._next_provisional = -2  # ids of hypotheses without a frame yet: -2, -3, ...
        self._provisional_segments = np.zeros(0, np.int64)
        self._born_ids = np.zeros(0, np.int64)
        # returns of each framed track's measurement this sweep, and what its class rests on
        self._seen_returns: dict[int, int] = {}
        self.class_evidence: dict[int, ClassEvidence] = {}
        self._denied_ids = np.zeros(0, np.int64)
        self.lost = LostObjects(ctx.config.reid)  # objects gone moments ago (sp.reid)
        self._revived: dict[int, Lost] = {}  # found again, not confirmed again yet

    # ------------------------------------------------------------------ windowing

    def window(
        self,
        shape: tuple[int, int],
        T_world_ladar: np.ndarray,
        row_el: np.ndarray,
        t_ns: int,
        attention_world_xyz: np.ndarray | None,
    ) -> np.ndarray:
        """(H, W) bool attention windows of this sweep: around the tracks' predicted
        positions (growing with their uncertainty), around ``attention_world_xyz`` (M, 3)
        world points (WM's surprises), and last sweep's unexplained pixels."""
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
            mask = window_mask(shape, c_s, np.concatenate(sig), row_el, self.ctx.config.window)
        if self.attention.shape == shape:
            mask |= self.attention
        return mask

    def predicted_people_xy(self, t_ns: int) -> np.ndarray:
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

    # ------------------------------------------------------------------ grouping

    def group(
        self,
        xyz_s: np.ndarray,
        range_m: np.ndarray,
        candidates: np.ndarray,
        row_el: np.ndarray,
        attention: np.ndarray,
    ) -> np.ndarray:
        """(H, W) int64 segment per pixel (-1 none) of the ``candidates`` (H, W) bool pixels
        (sensor-frame points ``xyz_s`` (H, W, 3) m, ``range_m`` (H, W)): contiguity and range
        steps; small segments are kept only inside the ``attention`` windows."""
        cfg = self.ctx.config
        seg_cfg = cfg.segments
        W = candidates.shape[1]
        labels = label_objects(
            xyz_s, range_m, candidates, row_step(row_el), 2 * math.pi / W, _with_min(seg_cfg, 1)
        )
        return _drop_small(labels, attention, seg_cfg.min_pixels, cfg.min_pixels_attended)

    # ------------------------------------------------------------------ computation

    def compute(
        self,
        t_ns: int,
        img: EgosphereImage,
        labels: np.ndarray,
        xyz_w: np.ndarray,
        xyz_g: np.ndarray,
        gp: GroundPixels,
        T_world_ladar: np.ndarray,
    ) -> Segments:
        """Attributes of the segments ``labels`` (H, W) (world points ``xyz_w``, gravity-aligned
        ``xyz_g``, (H, W, 3) m; level 3's ground ``gp``); pieces of one face or wall are
        merged, people walking side by side cut where their tracks predict them, and segments
        too low or terrain-like go to the ground. Far out, the ground the world model holds
        judges a segment's height better than the ground below it in its column: a segment
        of returns on the ground the model knows (``gp.on_known``,
        :class:`sp.ground_prior.GroundPriorConfig` ``on_ground_*``) is terrain, and one
        holding a ``gp.standing`` return is an object, however low, flat or on known ground."""
        cfg = self.ctx.config
        seg_cfg = cfg.segments
        valid = img.valid_first
        W = valid.shape[1]
        ground = gp.ground
        gz = ground_below(ground, xyz_w[..., 2], np.hypot(xyz_g[..., 0], xyz_g[..., 1]))
        inten = np.nan_to_num(img.intensity[..., 0])
        range0_m = np.where(valid, img.range_first, 0.0)
        t_off = img.t_offset_ns[..., 0]
        # a surface that something in front of it cut in two along a row is one
        behind = merge_behind_occluders(labels, range0_m, 2 * math.pi / W, seg_cfg)
        if behind.size and behind.max() + 1 < behind.size:
            labels = np.where(labels >= 0, behind[np.maximum(labels, 0)], -1)
        attrs = segment_attributes(labels, xyz_w, inten, range0_m, t_off, gz)
        # a face seen at a grazing angle breaks into strips along the line of sight: one face
        grazed = merge_grazing(
            attrs.center_xyz[:, :2], attrs.width_m, attrs.ground_z_m + attrs.height_m,
            T_world_ladar[:2, 3], 2 * math.pi / W, seg_cfg,
        )  # fmt: skip
        if grazed.size and grazed.max() + 1 < len(attrs):
            labels = np.where(labels >= 0, grazed[np.maximum(labels, 0)], -1)
            attrs = segment_attributes(labels, xyz_w, inten, range0_m, t_off, gz)
        # continuity: pieces of one wall or fence cut by occluders are one object
        merged = merge_collinear(
            attrs.center_xyz[:, :2], attrs.yaw_rad, attrs.length_m, attrs.width_m,
            attrs.range_m, seg_cfg,
        )  # fmt: skip
        if merged.size and merged.max() + 1 < len(attrs):
            labels = np.where(labels >= 0, merged[np.maximum(labels, 0)], -1)
            attrs = segment_attributes(labels, xyz_w, inten, range0_m, t_off, gz)
        # people walking side by side, joined by proximity, are cut where their tracks predict
        split = split_by_predictions(
            labels, xyz_w, self.predicted_people_xy(t_ns), attrs.center_xyz[:, :2],
            0.5 * np.hypot(attrs.length_m, attrs.width_m), cfg.split_near_m,
            cfg.split_min_apart_m, seg_cfg.min_pixels,
        )  # fmt: skip
        if split is not labels:
            labels = split
            attrs = segment_attributes(labels, xyz_w, inten, range0_m, t_off, gz)
        # ... and before either is tracked, where a gap between their returns shows two
        split = split_at_gap(
            labels, xyz_w, attrs.yaw_rad, attrs.length_m, attrs.width_m, attrs.height_m,
            cfg.gap_split_m, cfg.gap_split_max_length_m, cfg.gap_split_max_width_m,
            cfg.gap_split_min_height_m, 2 * seg_cfg.min_pixels,
        )  # fmt: skip
        if split is not labels:
            labels = split
            attrs = segment_attributes(labels, xyz_w, inten, range0_m, t_off, gz)
        # too low to stand out of the terrain (bumps, ruts), a gently sloping plane (a
        # hillside seen past a gap), on the ground the model knows or rising from the ground
        # as the ground does (a bank, a mound): ground, not objects. The first three not when
        # its row shows it standing: a low rock's one or two rows far out are low and flat,
        # and the model may have fused them as ground before that row showed it
        k = len(attrs)
        on = cfg.ground_prior
        on_known = count_in(labels, gp.on_known, k) >= on.on_ground_share * attrs.n_pixels
        low = (attrs.height_m < cfg.min_object_height_m) | terrain_patch(attrs, cfg)
        low |= on_known & (attrs.height_m < on.on_ground_below_m)
        low &= count_in(labels, gp.standing, k) == 0
        rise_deg, n_cols = foot_rise_deg(
            labels, xyz_g, valid, ground, len(attrs), seg_cfg.row_gap, cfg.foot_chord_m,
            cfg.foot_rise_m,
        )  # fmt: skip
        low |= (n_cols >= cfg.foot_min_columns) & (rise_deg < cfg.foot_object_deg)
        if low.any():
            flat_low = np.isin(labels, np.flatnonzero(low))
            ground = ground | flat_low
            remap = np.full(len(attrs), -1, dtype=np.int64)
            remap[~low] = np.arange(int((~low).sum()))
            labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
            attrs = attrs.take(~low)
        return Segments(labels, attrs, ground, segment_roughness(labels, range0_m, len(attrs)))

    # ------------------------------------------------------------------ filtering

    def filter(self, seg: Segments, t_ns: int, T_world_ladar: np.ndarray) -> ObjectsObserved:
        """Track the segments: associate with the predictions, update, confirm or deny; a
        hypothesis seen ``birth_hits`` times gets its frame (M-of-N birth). The tracks that
        ended are returned in ``finished`` for their parts (faces, lists) to go too."""
        ctx = self.ctx
        cfg = ctx.config
        a = seg.attributes
        self._sensor_xy = T_world_ladar[:2, 3].copy()  # partial views lie on its side
        what = np.stack([a.length_m, a.width_m, a.height_m, a.yaw_rad], axis=1)
        meas = Measurements(a.center_xyz, t_ns + a.t_offset_ns, what, a.range_m, a.n_pixels)

        def provisional_ids(n: int) -> np.ndarray:
            # a new hypothesis has no KD frame until it has been seen ``birth_hits`` times
            start = self._next_provisional
            self._next_provisional -= n
            return np.arange(start, start - n, -1, dtype=np.int64)

        track_of, prev = self.tracker.step(meas, t_ns, provisional_ids, self._sensor_xy)
        # two confirmed vehicles at rest standing closer than a body are pieces of one
        self.tracker.merge_pieces(self._of_class("vehicle"), cfg.merge_vehicle_within_m)
        # ... and two confirmed buildings whose footprints touch are faces of one
        self.tracker.merge_touching(self._of_class("building"), cfg.merge_building_gap_m)
        tr = self.tracker.tracks
        # M-of-N birth: hypotheses seen often enough get their frame (and "appeared") now; the
        # frame's id comes from the id source (the KD's), so images, tracks and frames share it
        promote = np.flatnonzero(
            (tr.id < 0)
            & ((tr.hits >= cfg.birth_hits) | (tr.status == TrackStatus.CONFIRMED))
            & (tr.status != TrackStatus.DENIED)
        )
        # ... unless it is an object lost moments ago, which takes up its frame again
        self.lost.forget_before(t_ns)
        found = self.lost.match(tr.t_ns[promote], tr.x[promote, :2], tr.w[promote, 2])
        born: list[int] = []
        for k, lost in zip(promote, found, strict=True):
            if lost is not None:
                oid = lost.id
                self._recall(lost)
            else:
                oid = ctx.new_entity(
                    f"object@{t_ns}",
                    Level.OBJECT,
                    images=(IMAGE_NAMES[4],),
                    confidence=unit(tr.confidence[k]),
                )
            tr.id[k] = oid
            prev[k] = -1
            born.append(oid)
        self._born_ids = np.array(born, dtype=np.int64)
        events: list[int] = []
        for i in born:
            if i not in self._revived:  # a lost object found again appears once confirmed
                events.append(ctx.event(EventClass.APPEARED, t_ns, [i], 4, cfg.tracker.confidence0))
        # only tracks with a frame are written: provisional ones stay inside the tracker
        framed = tr.id >= 0
        track_of = np.where(
            track_of >= 0, np.where(framed[np.maximum(track_of, 0)], track_of, -2), -1
        )
        # states of the tracks updated this cycle
        hit = np.flatnonzero(track_of >= 0)
        upd = np.unique(track_of[hit])
        self._seen_returns = {int(tr.id[track_of[j]]): int(a.n_pixels[j]) for j in hit}
        # tracks the stationarity test finds at rest, and objects of classes fixed where
        # they stand, are reported at zero speed
        x_rep, P_rep = tr.reported(cfg.tracker, self._of_class(*cfg.fixed_classes))
        if upd.size:
            yaw = tr.w[upd, 3]
            moving = np.hypot(x_rep[upd, 3], x_rep[upd, 4]) > 1.0
            yaw = np.where(moving, np.arctan2(x_rep[upd, 4], x_rep[upd, 3]), yaw)
            q = np.stack([matrix_to_quat(rot_z(float(y))) for y in yaw])
            var_rpy = np.zeros((upd.size, 3))
            var_rpy[:, 2] = tr.Pw[upd, 3]
            ctx.record(
                StatesObserved(
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
            )
        # frames: status, confidence, attributes
        seg_of_track = largest_segment_of_track(track_of, a.n_pixels, len(tr))
        for k in np.flatnonzero(framed):
            tid = int(tr.id[k])
            status = KD_STATUS[TrackStatus(int(tr.status[k]))]
            was = int(prev[k])
            s = seg_of_track[k]
            attributes = None
            if s >= 0:
                rough = float(seg.roughness_m[s])
                attributes = _attributes(a, s, rough, tr.w[k], tr.Pw[k], x_rep[k])
                self.observe_appearance(self.track_reflectance, tid, float(a.intensity[s]))
                self.observe_shape(tid, a, int(s))
                self.observe_appearance(self.track_roughness, tid, rough)
            confidence = unit(tr.confidence[k])
            if tid in self._revived:
                if status != Status.CONFIRMED:
                    # a lost object found again stays gone until its track is confirmed, and
                    # for good if it is denied: its confirmed life stands
                    ctx.record(FrameChange(tid, Status.GONE, confidence, attributes))
                    continue
                del self._revived[tid]
                events.append(ctx.event(EventClass.APPEARED, t_ns, [tid], 4, confidence))
            ctx.record(FrameChange(tid, status, confidence, attributes))
            if was == int(status_code(status)) or (was < 0 and status == Status.HYPOTHESIZED):
                continue
            cls = {
                Status.CONFIRMED: EventClass.CONFIRMED,
                Status.DENIED: EventClass.DENIED,
                Status.GONE: EventClass.VANISHED,
            }.get(status)
            if cls is not None:
                events.append(ctx.event(cls, t_ns, [tid], 4, float(tr.confidence[k])))
        finished = self.tracker.drop_finished()
        self._denied_ids = finished.id[(finished.status == TrackStatus.DENIED) & (finished.id >= 0)]
        self._remember_lost(finished)
        for tid in finished.id:
            self._forget_track(int(tid))
        self._provisional_segments = np.flatnonzero(track_of == -2)
        # object id per segment
        ids_all = np.concatenate([tr.id])
        obj = np.full(len(meas), -1, dtype=np.int64)
        ok = track_of >= 0
        obj[ok] = ids_all[track_of[ok]]
        return ObjectsObserved(obj, events, finished.id.astype(np.int64))

    def _per_track(self) -> dict[str, dict]:
        """What this level keeps of each framed track, by name."""
        return {
            "class": self.track_class,
            "evidence": self.class_evidence,
            "reflectance": self.track_reflectance,
            "camera": self.track_camera,
            "excess_green": self.track_excess_green,
            "shape": self.track_shape,
            "roughness": self.track_roughness,
        }

    def _forget_track(self, tid: int) -> dict:
        """Drop what this level keeps of track ``tid``; returns it, by name."""
        kept = {}
        for name, table in self._per_track().items():
            if tid in table:
                kept[name] = table.pop(tid)
        return kept

    def _recall(self, lost: Lost) -> None:
        """Object ``lost``, found again, takes back what this level kept of it."""
        tables = self._per_track()
        for name, value in lost.kept.items():
            tables[name][lost.id] = value
        self._revived[lost.id] = lost

    def _remember_lost(self, finished: Tracks) -> None:
        """The framed tracks of ``finished`` that went unseen until gone (not those denied,
        nor those gone while still measured: they had lost their object) are remembered for
        :mod:`sp.reid`, with their class, appearance and shape."""
        cfg = self.ctx.config
        for tid in finished.id[finished.status == TrackStatus.DENIED].tolist():
            # found again by a hypothesis that was denied: still lost as it was
            lost = self._revived.pop(int(tid), None)
            if lost is not None:
                lost.kept = self._forget_track(int(tid))
                self.lost.add(lost)
        gone = np.flatnonzero(
            (finished.status == TrackStatus.GONE) & (finished.id >= 0) & (finished.misses > 0)
        )
        if not gone.size:
            return
        # a building lost while its filter drifted is remembered where it stands, at rest
        fixed = self._ids_of_class(finished.id, *cfg.fixed_classes)
        x_rep, _ = finished.reported(cfg.tracker, fixed)
        moving = finished.moving(cfg.tracker, fixed)
        for j in gone.tolist():
            tid = int(finished.id[j])
            self.lost.add(
                Lost(tid, int(finished.t_ns[j]), x_rep[j, :2].copy(), x_rep[j, 3:5].copy(),
                     float(finished.w[j, 2]), bool(moving[j]), self._forget_track(tid))
            )  # fmt: skip

    def _of_class(self, *names: str) -> np.ndarray:
        """(T,) bool: the tracks whose class (as last classified) is one of ``names`` or a kind
        of one (none for a name the class library does not hold)."""
        return self._ids_of_class(self.tracker.tracks.id, *names)

    def _ids_of_class(self, ids: np.ndarray, *names: str) -> np.ndarray:
        """(N,) bool: the tracks of ``ids`` (N,) int64 whose class (as last classified) is
        one of ``names`` or a kind of one."""
        lib = self.ctx.classes
        kinds = set().union(*(lib.descendants(n) for n in names if n in lib))
        no_class = (None, 0.0)
        return np.array(
            [self.track_class.get(tid, no_class)[0] in kinds for tid in ids.tolist()], dtype=bool
        )

    # ------------------------------------------------------------------ classification

    def classify(self, t_ns: int) -> list[int]:
        """Class of every framed track (all at once: a class founded here takes part from
        the next sweep on); a class changes only for a score better by
        ``reclassify_margin`` on evidence as good as what it rests on
        (:class:`ClassEvidence`, ``reclassify_min_share``), and a confirmed object matching
        nothing founds a specific class. Returns the ids of the "reclassified" events."""
        ctx = self.ctx
        cfg = ctx.config
        self.refresh_classes()
        tr = self.tracker.tracks
        events: list[int] = []
        ks, rows = self.class_rows()
        # the measured views of confirmed objects count towards the scene's class mix
        counted = (tr.status[ks] == TrackStatus.CONFIRMED) & np.array(
            [self._seen_returns.get(int(i), 0) > 0 for i in tr.id[ks]], dtype=bool
        )
        matches = self.classifier.classify_many(
            rows, self._scene_prior(), np.where(counted, tr.id[ks], -1)
        )
        for k, m in zip(ks, matches, strict=True):
            tid = int(tr.id[k])
            old, _ = self.track_class.get(tid, (None, -2.0))
            confirmed = tr.status[k] == TrackStatus.CONFIRMED
            if m.name is None:
                continue
            seen = self._seen_returns.get(tid, 0)
            evidence = self.class_evidence.setdefault(tid, ClassEvidence())
            if seen:
                evidence.observe(m.name, old, seen)
            if old is not None and m.name != old:
                if m.score < m.scores.get(old, -2.0) + cfg.reclassify_margin:
                    continue
                if not evidence.may_change(old, m.name, seen, cfg.reclassify_min_share):
                    continue
            if m.name == old:
                self.track_class[tid] = (old, m.score)
                continue
            evidence.take(m.name, seen)
            self.track_class[tid] = (m.name, m.score)
            ctx.set_class(tid, m.name)
            proto = ctx.classes.get(m.name)
            specific = m.name if proto.kind == ClassKind.SPECIFIC else None
            ctx.record(
                FrameChange(
                    tid, generic_classes=m.generic, specific_class=specific, sets_specific=True
                )
            )
            if old is not None and confirmed:
                events.append(ctx.event(EventClass.RECLASSIFIED, t_ns, [tid], 4, unit(m.score)))
            if confirmed and cfg.found_specific and m.fit < cfg.classify.match and specific is None:
                ctx.record(ClassFounded(tid))
                ctx.classes_founded = True
        return events

    def _scene_prior(self) -> ScenePrior | None:
        """The scene prior for the classifier's discriminant (a new one, started at the
        training prior, when the discriminant changed); None when the configuration keeps the
        training prior or the discriminant does not state it."""
        disc = self.classifier.disc
        cfg = self.ctx.config.classify
        if (
            disc is None
            or disc.prior is None
            or disc.views is None
            or cfg.scene_prior_strength is None
        ):
            return None
        if self.scene_prior is None or self.scene_prior.classes != disc.classes:
            self.scene_prior = ScenePrior(
                disc.classes,
                disc.prior,
                disc.views,
                cfg.scene_prior_strength,
                cfg.scene_prior_window,
            )
        return self.scene_prior

    def class_rows(self) -> tuple[np.ndarray, list[dict[str, float]]]:
        """The attributes every framed track is classified by: its tracker slots (K,) and,
        per slot, attribute name -> value (units in the names; an attribute never observed
        is left out). Extents are the filter's, speed the one its sequential test supports
        (:meth:`sp.tracking.Tracks.tested_speed`), appearance and shape the running means of
        :meth:`appearance_of` and :meth:`shape_of`."""
        tr = self.tracker.tracks
        ks = np.flatnonzero(tr.id >= 0)
        speeds = tr.tested_speed(self.ctx.config.tracker)[ks]
        rows = []
        for k, speed in zip(ks, speeds.tolist(), strict=True):
            l, w, h = (float(v) for v in tr.w[k, :3])
            rows.append(
                {"height_m": h, "width_m": w, "length_m": l, "speed_mps": speed}
                | self.appearance_of(int(tr.id[k]))
                | self.shape_of(int(tr.id[k]))
            )
        return ks, rows

    def refresh_classes(self) -> bool:
        """Take in the specific classes the world model founded from earlier observations
        (:class:`~sp.observations.ClassFounded`, now in the class library): the classifier and
        the class names. True when there were any."""
        if not self.ctx.classes_founded:
            return False
        self.classifier.refresh()
        self.ctx.refresh_classes()
        self.ctx.classes_founded = False
        return True

    # ------------------------------------------------------------------ the entity image

    def entity_image(self, labels: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """(H, W) int64 level-4 entity image: the object id of each pixel's segment
        (``labels`` (H, W), ``ids`` (K,) per segment), -1 none; a hypothesis denied this
        sweep releases its pixels."""
        image4 = np.full(labels.shape, -1, dtype=np.int64)
        has = labels >= 0
        image4[has] = ids[labels[has]]
        denied = self._denied_ids
        if denied.size:
            image4[np.isin(image4, denied)] = -1
        return image4

    def confirmed_ids(self) -> np.ndarray:
        """Ids of the confirmed tracks (int64)."""
        tr = self.tracker.tracks
        return tr.id[tr.status == TrackStatus.CONFIRMED]

    def confirmed_pixels(self, image4: np.ndarray) -> np.ndarray:
        """(H, W) bool pixels of confirmed objects (one gather through a table by id)."""
        tr = self.tracker.tracks
        ids = tr.id[(tr.status == TrackStatus.CONFIRMED) & (tr.id >= 0)]
        if ids.size == 0:
            return np.zeros(image4.shape, dtype=bool)
        lut = np.zeros(max(int(ids.max()), int(image4.max(initial=0))) + 1, dtype=bool)
        lut[ids] = True
        return lut[np.maximum(image4, 0)] & (image4 >= 0)

    def unexplained(self, labels: np.ndarray, image4: np.ndarray) -> None:
        """New and provisional hypotheses of this sweep draw attention in the next one."""
        provisional = np.isin(labels, self._provisional_segments)
        self.attention = ((labels >= 0) & np.isin(image4, self._born_ids)) | provisional

    # ------------------------------------------------------------------ appearance

    def appearance(
        self,
        points_world: np.ndarray,
        point_ids: np.ndarray,
        camera: CameraFrame,
        T_world_camera: np.ndarray,
    ) -> None:
        """Camera intensity, coverage and excess green of the confirmed objects of this
        cycle, observed from the world points (N, 3) and their object ids (N,) (-1 none)."""
        tr = self.tracker.tracks
        confirmed = tr.id[(tr.status == TrackStatus.CONFIRMED) & (tr.id >= 0)]
        sel = np.isin(point_ids, confirmed)
        if not sel.any():
            return
        a = object_appearance(points_world[sel], point_ids[sel], camera, T_world_camera)
        seen = zip(a.ids, a.intensity, a.coverage, a.excess_green, strict=True)
        for oid, inten, cov, green in seen:
            self.ctx.record(AppearanceObserved(int(oid), float(inten), float(cov), float(green)))
            self.observe_appearance(self.track_camera, int(oid), float(inten))
            self.observe_appearance(self.track_excess_green, int(oid), float(green))

    def observe_appearance(self, table: dict[int, float], tid: int, value: float) -> None:
        """Running mean (exponential, ``appearance_gain``) of an object's observed appearance
        (LADAR intensity or camera grey) or texture, for classification; an unknown value
        (NaN) leaves it as it was."""
        if not math.isfinite(value):
            return
        old = table.get(tid)
        gain = self.ctx.config.appearance_gain
        table[tid] = value if old is None else old + gain * (value - old)

    def observe_shape(self, tid: int, a: SegmentAttributes, s: int) -> None:
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
        gain = self.ctx.config.appearance_gain
        new = np.where(np.isnan(old), v, old + gain * (v - old))
        if not surface:
            new[:_SURFACE_KEYS] = old[:_SURFACE_KEYS]
        new[-1] = np.fmax(old[-1], v[-1])
        self.track_shape[tid] = new

    def shape_of(self, tid: int) -> dict[str, float]:
        """The shape attributes object ``tid`` has been observed with (none if never): those
        of :data:`SHAPE_KEYS` and ``roughness_m``, the running mean of its texture."""
        v = self.track_shape.get(tid)
        out = {}
        if v is not None:
            out = {k: float(x) for k, x in zip(SHAPE_KEYS, v, strict=True) if np.isfinite(x)}
        if tid in self.track_roughness:
            out["roughness_m"] = self.track_roughness[tid]
        return out

    def appearance_of(self, tid: int) -> dict[str, float]:
        """The appearance attributes object ``tid`` has been observed with: ``reflectance``
        (mean LADAR intensity over ``intensity_per_reflectance``, when that is known),
        ``camera_intensity`` (mean grey 0..1 of its returns in the camera image) and
        ``camera_excess_green`` (their excess green in a colour image). An
        attribute never observed is left out, so the classifier ignores it rather than
        reading it as zero."""
        cfg = self.ctx.config
        if not cfg.appearance_classes:
            return {}
        out = {}
        if tid in self.track_reflectance and cfg.intensity_per_reflectance:
            out["reflectance"] = self.track_reflectance[tid] / cfg.intensity_per_reflectance
        if tid in self.track_camera:
            out["camera_intensity"] = self.track_camera[tid]
        if tid in self.track_excess_green:
            out["camera_excess_green"] = self.track_excess_green[tid]
        return out


def status_code(s: Status) -> int:
    """The tracker's status code of KD status ``s``."""
    return {
        Status.HYPOTHESIZED: TrackStatus.HYPOTHESIZED,
        Status.CONFIRMED: TrackStatus.CONFIRMED,
        Status.DENIED: TrackStatus.DENIED,
        Status.GONE: TrackStatus.GONE,
    }[s]


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


def largest_segment_of_track(
    track_of: np.ndarray, n_pixels: np.ndarray, n_tracks: int
) -> np.ndarray:
    """(n_tracks,) int64: for each track the segment that speaks for its observed attributes
    and shape this sweep, -1 for none. ``track_of`` (K,) int64 is each segment's track (< 0
    none), ``n_pixels`` (K,) its returns. Pieces that joined a track's footprint (a sliver of
    a car's far side, a strip of a face) are parts of its object, not views of it: the
    track's largest segment is taken (ties: the later segment)."""
    out = np.full(n_tracks, -1, dtype=np.int64)
    mine = np.flatnonzero(track_of >= 0)
    # by track, then by size (a stable sort: ties keep the later segment last); the last of
    # each track's run is its largest (numpy leaves repeated-index assignment unordered)
    mine = mine[np.lexsort((n_pixels[mine], track_of[mine]))]
    t = track_of[mine]
    last = np.r_[t[1:] != t[:-1], True] if len(t) else np.zeros(0, dtype=bool)
    out[t[last]] = mine[last]
    return out


def _attributes(
    a: SegmentAttributes, s: int, roughness_m: float, w: np.ndarray, Pw: np.ndarray, x: np.ndarray
) -> dict[str, Attribute]:
    """Observed (this segment ``s``, whose texture is ``roughness_m``, NaN unknown) and
    estimated (the what-filter) attributes of one object."""
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
    if math.isfinite(roughness_m):
        out["roughness_m"] = Attribute(observed=roughness_m)
    return out

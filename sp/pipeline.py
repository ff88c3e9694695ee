"""Sensory processing levels 1 to 5 on one LADAR sweep: the orchestrator of the level modules.

Reference 001, 4.5.1-4.5.4 (the five SP functions: windowing, grouping, computation,
filtering, classification; hypothesize and test; recursive estimation), 4.4.4-4.4.5 (entity
images whose pixels hold frame ids, frames that point back to their images), 4.5.6 (levels 1
to 5). One call of :meth:`SensoryProcessor.process` is one cycle, the levels in this order:

1. level 1: the egosphere image of the sweep (:mod:`sp.egosphere`), its points to the world
   frame (:mod:`sp.sweep_points`);
2. level 3 grouping of the ground (:meth:`sp.level3_surfaces.SurfaceLevel.ground_pixels`);
3. level 4, objects (:mod:`sp.level4_objects`): windowing, grouping, computation, filtering
   (a hypothesis becomes an entity, with an "appeared" event, only once seen ``birth_hits``
   times), classification; an object that ends takes its face and lists with it;
4. level 3, surfaces (:mod:`sp.level3_surfaces`): the ground entity, the objects' faces,
   the free-standing surfaces, their contact boundaries and creases;
5. level 2, lists (:mod:`sp.level2_lists`): range and brightness edges, vertices, patches;
6. level 5, groups of objects (:mod:`sp.level5_groups`);
7. the entity images of levels 2-5, and from them the class and value images (:mod:`sp.images`);
8. with a camera frame: the confirmed objects' appearance (:mod:`sp.appearance`).

Each level module holds its own state (trackers, tables); the levels share an
:class:`~sp.context.SPContext` (configuration, class library and table, id source, sweep
count). SP holds no knowledge database: it is given the class library and an id source, the
levels observe new entities, their attributes, states, classes, relations and events
(:mod:`sp.observations`), in order, and the result carries them (``SPResult.observations``)
for the world model, which alone writes the KD (:class:`wm.entities.EntityUpdater`,
reference 001, 4.2). New frames' ids come from the id source as they are observed (the world
model gives the KD's ``new_id``). What SP needs to know of the KD's frames afterwards it
is told: which observations were written (:meth:`SensoryProcessor.observations_written`) and
which frames short-term memory forgot (:meth:`SensoryProcessor.frames_forgotten`).

Deskewing: ``T_world_ladar`` is the sensor pose at ``pose_t_ns`` (the sweep's stamp unless the
caller says otherwise). The world model's node deskews each sweep once on its pose track and
gives SP those points (``points_world``), so SP and the maps see the same points. Without them,
each column of the image, which fired at its own time, goes to the world with the pose at
that time, interpolated (or extrapolated) at constant velocity between the previous sweep's
pose and this one (:func:`column_poses`), so a static object does not smear or jump by the
vehicle's motion during the sweep (up to a metre at 10 m/s); the first sweep, or one after a
gap of more than ``deskew_max_gap_s``, is taken at the one pose. Each object's state is
stamped at the mean time of its own returns.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from core.errors import EngineError
from core.geometry import check_pose, interpolate_pose
from kd_store import ClassLibrary
from logs.types import CameraFrame, LadarScan
from sp.context import IMAGE_NAMES, SPConfig, SPContext
from sp.egosphere import EgosphereImage, to_egosphere
from sp.images import ClassTable, LazyImages, class_image, class_values, value_images
from sp.level2_lists import ListLevel
from sp.level3_surfaces import SurfaceLevel
from sp.level4_objects import ObjectLevel
from sp.level5_groups import GroupLevel
from sp.observations import NewEntity, Observation
from sp.sweep_points import sweep_points
from sp.tracking import Tracker

__all__ = ["PipelineError", "SPConfig", "SPResult", "SensoryProcessor", "column_poses"]

log = logging.getLogger(__name__)


class PipelineError(EngineError, ValueError):
    """A sweep or pose the pipeline cannot use; names the value and the sweep's time."""


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
    events:            ids of the events observed this cycle (their frames are written by WM).
    timings_s:         seconds per stage.
    point_pixel:       (N,) int64 flat pixel index of each point; point_index (N,) its index
                       in the sweep.
    attention_mask:    (H, W) bool windows used this cycle.
    class_names:       the class names ``point_class_ids`` index.
    observations:      what the levels observed, in order, for the world model to write into
                       the KD (:mod:`sp.observations`); kept for a failed sweep too (what it
                       observed before it failed).
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
    observations: list[Observation] = field(default_factory=list)
    ok: bool = True


class _Clock:
    def __init__(self) -> None:
        self.t = time.perf_counter()
        self.laps: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = self.laps.get(name, 0.0) + now - self.t
        self.t = now


class SensoryProcessor:
    """SP levels 1-5 over LADAR sweeps: the level modules (``level2`` ... ``level5``) called
    in order, once per sweep. ``classes`` is the class library the world model keeps (SP
    reads it; the world model adds the specific classes it founds), ``new_id`` the source of
    new frame ids (the world model's KD's ``new_id``). The results' observations are for
    :class:`wm.entities.EntityUpdater` to write into the KD."""

    def __init__(
        self,
        classes: ClassLibrary,
        new_id: Callable[[], int],
        config: SPConfig | None = None,
    ) -> None:
        self.ctx = SPContext(classes, new_id, config or SPConfig())
        self.level2 = ListLevel(self.ctx)
        self.level3 = SurfaceLevel(self.ctx, self.level2)
        self.level4 = ObjectLevel(self.ctx)
        self.level5 = GroupLevel(self.ctx)
        self._values: tuple[int, dict[str, np.ndarray]] = (-1, {})
        self._last_pose: tuple[int, np.ndarray] | None = None
        self.n_failed = 0

    @property
    def classes(self) -> ClassLibrary:
        """The class library SP classifies with."""
        return self.ctx.classes

    @property
    def config(self) -> SPConfig:
        return self.ctx.config

    @property
    def class_names(self) -> list[str]:
        """The class names the results' class indices refer to (grows as classes are founded)."""
        return self.ctx.class_names

    @property
    def class_table(self) -> ClassTable:
        return self.ctx.class_table

    @property
    def tracker(self) -> Tracker:
        """Level 4's object tracker."""
        return self.level4.tracker

    def observations_written(self, result: SPResult, n_written: int | None = None) -> None:
        """The world model has written ``result``'s observations into the KD, the first
        ``n_written`` of them (None: all; fewer when the KD refused one and the rest were
        skipped, :meth:`not_written`): a specific class founded from them joins SP's classes
        now (the classifier, ``class_names``, and the result's ``class_names``)."""
        if n_written is not None and n_written < len(result.observations):
            self.not_written(result.observations[n_written:])
        if self.level4.refresh_classes():
            result.class_names = self.class_names

    def not_written(self, observations: Sequence[Observation]) -> None:
        """The world model could not write ``observations`` into the KD: the lists and groups
        whose making is among them have no frame there, and the groups keep the status and
        confidence their frames hold."""
        ops = list(observations)
        made = [op.entity_id for op in ops if isinstance(op, NewEntity)]
        self.level2.frames_let_go(np.array(made, dtype=np.int64))
        self.level5.not_written(ops)

    def frames_forgotten(self, frame_ids: Sequence[int] | np.ndarray) -> None:
        """The KD's short-term memory forgot frames ``frame_ids`` (what the KD's
        ``advance`` returns): a list among them is released when next seen, as if denied."""
        self.level2.frames_let_go(np.asarray(frame_ids, dtype=np.int64))

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
        points_world: np.ndarray | None = None,
    ) -> SPResult:
        """One cycle on one sweep (points in the sensor frame, ``T_world_ladar`` the sensor pose
        at ``pose_t_ns``, by default ``scan.t_ns``). ``points_world`` (N, 3) float m: the
        sweep's points already deskewed into the world by the caller, in the scan's order (the
        node deskews each sweep once, for its maps and for SP); without it SP deskews each
        column itself (module docstring). A sweep that fails is logged and skipped;
        the tracks are kept. With a camera frame and its pose, each confirmed object's returns
        are projected into it for its camera intensity and coverage (:mod:`sp.appearance`); a
        camera frame that fails is logged and skipped, the sweep's result kept."""
        try:
            T = check_pose(np.asarray(T_world_ladar, dtype=np.float64), "T_world_ladar")
            t_pose = int(scan.t_ns if pose_t_ns is None else pose_t_ns)
            result = self._process(scan, T, t_pose, attention_world_xyz, points_world)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as e:
            return self._failed(scan, e)
        if camera is not None and T_world_camera is not None:
            try:
                self.level4.appearance(
                    result.points_world, result.point_entity_ids, camera, T_world_camera
                )
            except (ValueError, np.linalg.LinAlgError) as e:  # the camera frame is skipped
                self.n_failed += 1
                log.warning("SP skipped the camera frame at t_ns=%s: %s", camera.t_ns, e)
        result.observations = self.ctx.take_observations()
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
            observations=self.ctx.take_observations(),
            ok=False,
        )

    def _process(
        self,
        scan: LadarScan,
        T_world_ladar: np.ndarray,
        pose_t_ns: int,
        attention_world_xyz: np.ndarray | None,
        points_world: np.ndarray | None = None,
    ) -> SPResult:
        cfg = self.config
        l2, l3, l4, l5 = self.level2, self.level3, self.level4, self.level5
        clock = _Clock()
        t_ns = int(scan.t_ns)
        # level 1: the egosphere image and its points in the world and gravity-aligned frames
        img = to_egosphere(scan, cfg.egosphere)
        valid = img.valid_first
        if points_world is None:
            T_cols = self._column_poses(img, t_ns, T_world_ladar, pose_t_ns)
        else:  # the caller's deskew: the maps' points and SP's are the same points
            self._last_pose, T_cols = (pose_t_ns, T_world_ladar), T_world_ladar[None]
        xyz_s, xyz_g, xyz_w, row_el = sweep_points(img, T_world_ladar[:3, :3], T_cols)
        if points_world is not None:
            _place(xyz_w, img, points_world, scan.n_points)
        range_m = np.where(valid, img.range_first, np.inf)
        clock.lap("egosphere")
        ground = l3.ground_pixels(xyz_g, valid)
        clock.lap("ground")

        # level 4: the five SP functions in turn
        attention = l4.window(valid.shape, T_world_ladar, row_el, t_ns, attention_world_xyz)
        clock.lap("windowing")
        candidates = valid & ~ground & (range_m <= cfg.max_object_range_m)
        labels = l4.group(xyz_s, range_m, candidates, row_el, attention)
        clock.lap("grouping")
        seg = l4.compute(t_ns, img, labels, xyz_w, xyz_g, ground, T_world_ladar)
        clock.lap("computation")
        objects = l4.filter(seg, t_ns, T_world_ladar)
        for oid in objects.finished.tolist():  # an object's face and lists go with it
            l3.object_gone(oid)
            l2.owner_gone(oid)
        clock.lap("filtering")
        events = objects.events + l4.classify(t_ns)
        clock.lap("classification")

        image4 = l4.entity_image(seg.labels, objects.ids)
        in_object = l4.confirmed_pixels(image4)
        surfaces = l3.step(
            t_ns, xyz_w, xyz_g, valid, seg.ground, seg.labels, seg.attributes, objects.ids,
            l4.confirmed_ids(), in_object, T_world_ladar, row_el,
        )  # fmt: skip
        clock.lap("level3")
        image2 = np.full(valid.shape, -1, dtype=np.int64)
        if cfg.lists:
            owner = np.where(in_object, image4, surfaces.image)
            intensity = img.intensity[..., 0]
            image2 = l2.step(t_ns, owner, range_m, valid, intensity, surfaces.free_px).image
        has_contact = surfaces.contact >= 0
        image2[has_contact] = surfaces.contact[has_contact]
        self.ctx.sweep += 1
        clock.lap("level2")
        groups = l5.step(t_ns, image4, l4)
        events += groups.events
        clock.lap("groups")

        l4.unexplained(seg.labels, image4)
        entity_images = {2: image2, 3: surfaces.image, 4: image4, 5: groups.image}
        result = self._result(
            t_ns, img, xyz_w, entity_images, seg.ground, surfaces.surfaces, events, attention
        )
        clock.lap("images")
        result.timings_s = clock.laps
        return result

    def _result(
        self,
        t_ns: int,
        img: EgosphereImage,
        xyz_w: np.ndarray,
        entity_images: dict[int, np.ndarray],
        ground: np.ndarray,
        surfaces: list[int],
        events: list[int],
        attention: np.ndarray,
    ) -> SPResult:
        """The cycle's result: the entity images (level -> (H, W) int64), their class and
        value images, and per valid pixel its world point (of ``xyz_w`` (H, W, 3) m), object
        and class."""
        flat = np.flatnonzero(img.valid_first.reshape(-1))
        pe = entity_images[4].reshape(-1)[flat]
        class_images, values, point_class = self._class_images(entity_images, flat)
        return SPResult(
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
            self._values = (len(self.class_names), class_values(self.classes, self.class_names))
        return self._values[1]


def _place(xyz_w: np.ndarray, img: EgosphereImage, points_world: np.ndarray, n: int) -> None:
    """Overwrite the world point (H, W, 3) of every pixel with a return by the caller's
    deskewed point of that return (``points_world`` (n, 3) m, the scan's order)."""
    pw = np.asarray(points_world)
    if pw.shape != (n, 3):
        raise PipelineError(f"points_world has shape {pw.shape}; the sweep has {n} points")
    first = img.point_index[..., 0]
    has = first >= 0
    xyz_w[has] = pw[first[has]]


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

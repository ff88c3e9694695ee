"""Sensory processing levels 1 to 5 on one LADAR sweep: the orchestrator of the level modules.

Reference 001, 4.5.1-4.5.4 (the five SP functions: windowing, grouping, computation,
filtering, classification; hypothesize and test; recursive estimation), 4.4.4-4.4.5 (entity
images whose pixels hold frame ids, frames that point back to their images), 4.5.6 (levels 1
to 5). One call of :meth:`SensoryProcessor.process` is one cycle, the levels in this order:

1. level 1 (:mod:`sp.level1`): the egosphere image of the sweep (:mod:`sp.egosphere`), its
   points to the world frame, deskewed (:mod:`sp.sweep_points`);
2. level 3 grouping of the ground (:meth:`sp.level3_surfaces.SurfaceLevel.ground_pixels`);
3. level 4, objects (:mod:`sp.level4_objects`): windowing, grouping, computation, filtering
   (a hypothesis becomes an entity, with an "appeared" event, only once seen ``birth_hits``
   times), classification; an object that ends takes its face and lists with it;
4. level 3, surfaces (:mod:`sp.level3_surfaces`): the ground entity, the objects' faces,
   the free-standing surfaces, their contact boundaries and creases;
5. level 2, lists (:mod:`sp.level2_lists`): range and brightness edges, vertices, patches;
6. level 5, groups of objects (:mod:`sp.level5_groups`);
7. the result (:mod:`sp.result`): the entity images of levels 2-5, and from them the class
   and value images (:mod:`sp.images`);
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
level 1 moves each column of the image, which fired at its own time, to the world with the
pose at that time, at constant velocity between the previous sweep's pose and this one
(:func:`sp.level1.column_poses`, re-exported here); the first sweep, or one after a gap of
more than ``deskew_max_gap_s``, is taken at the one pose. Each object's state is stamped at
the mean time of its own returns.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import numpy as np

from core.geometry import check_pose
from kd_store import ClassLibrary
from logs.types import CameraFrame, LadarScan
from sp.context import SPConfig, SPContext
from sp.ground_prior import GroundPrior
from sp.images import ClassTable
from sp.level1 import PixelLevel, PixelsObserved, column_poses
from sp.level1 import PixelLevelError as PipelineError
from sp.level2_lists import ListLevel
from sp.level3_surfaces import SurfaceLevel, SurfacesObserved
from sp.level4_objects import ObjectLevel, Segments
from sp.level5_groups import GroupLevel
from sp.observations import NewEntity, Observation
from sp.result import ResultMaker, SPResult
from sp.tracking import Tracker

# PipelineError, SPResult and column_poses live in sp.level1 and sp.result; they are
# exported here too, where callers of SensoryProcessor find them
__all__ = ["PipelineError", "SPConfig", "SPResult", "SensoryProcessor", "column_poses"]

log = logging.getLogger(__name__)


class _Clock:
    """Seconds per named stage of one cycle (the result's ``timings_s``)."""

    def __init__(self) -> None:
        self.t = time.perf_counter()
        self.laps: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = self.laps.get(name, 0.0) + now - self.t
        self.t = now


class SensoryProcessor:
    """SP levels 1-5 over LADAR sweeps: the level modules (``level1`` ... ``level5``) called
    in order, once per sweep, and ``results`` assembling each sweep's :class:`SPResult`.
    ``classes`` is the class library the world model keeps (SP reads it; the world model adds
    the specific classes it founds), ``new_id`` the source of new frame ids (the world model's
    KD's ``new_id``). The results' observations are for :class:`wm.entities.EntityUpdater` to
    write into the KD."""

    def __init__(
        self,
        classes: ClassLibrary,
        new_id: Callable[[], int],
        config: SPConfig | None = None,
    ) -> None:
        self.ctx = SPContext(classes, new_id, config or SPConfig())
        self.level1 = PixelLevel(self.ctx.config)
        self.level2 = ListLevel(self.ctx)
        self.level3 = SurfaceLevel(self.ctx, self.level2)
        self.level4 = ObjectLevel(self.ctx)
        self.level5 = GroupLevel(self.ctx)
        self.results = ResultMaker(self.ctx)
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
        ground_prior: GroundPrior | None = None,
    ) -> SPResult:
        """One cycle on one sweep (points in the sensor frame, ``T_world_ladar`` the sensor pose
        at ``pose_t_ns``, by default ``scan.t_ns``). ``points_world`` (N, 3) float m: the
        sweep's points already deskewed into the world by the caller, in the scan's order (the
        node deskews each sweep once, for its maps and for SP); without it SP deskews each
        column itself (module docstring). A sweep that fails is logged and skipped;
        the tracks are kept. With a camera frame and its pose, each confirmed object's returns
        are projected into it for its camera intensity and coverage (:mod:`sp.appearance`); a
        camera frame that fails is logged and skipped, the sweep's result kept. ``ground_prior``:
        the ground the world model expects (its terrain map, :mod:`sp.ground_prior`), for the
        ground of far returns."""
        try:
            T = check_pose(np.asarray(T_world_ladar, dtype=np.float64), "T_world_ladar")
            t_pose = int(scan.t_ns if pose_t_ns is None else pose_t_ns)
            result = self._process(scan, T, t_pose, attention_world_xyz, points_world, ground_prior)
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
        t_ns = int(getattr(scan, "t_ns", 0))
        return self.results.failed(t_ns, self.ctx.take_observations())

    def _process(
        self,
        scan: LadarScan,
        T_world_ladar: np.ndarray,
        pose_t_ns: int,
        attention_world_xyz: np.ndarray | None,
        points_world: np.ndarray | None = None,
        ground_prior: GroundPrior | None = None,
    ) -> SPResult:
        """The cycle's levels in order (module docstring), each stage timed."""
        l3, l4, T = self.level3, self.level4, T_world_ladar
        clock = _Clock()
        t_ns = int(scan.t_ns)
        px = self.level1.step(scan, T, pose_t_ns, points_world)
        clock.lap("egosphere")
        gp = l3.ground_pixels(px.xyz_g, px.valid, px.xyz_w, px.range_m, ground_prior)
        ground = gp.ground
        clock.lap("ground")

        # level 4: the five SP functions in turn
        attention = l4.window(px.valid.shape, T, px.row_el, t_ns, attention_world_xyz)
        clock.lap("windowing")
        candidates = px.valid & ~ground & (px.range_m <= self.config.max_object_range_m)
        labels = l4.group(px.xyz_s, px.range_m, candidates, px.row_el, attention)
        clock.lap("grouping")
        seg = l4.compute(t_ns, px.img, labels, px.xyz_w, px.xyz_g, gp, T)
        clock.lap("computation")
        objects = l4.filter(seg, t_ns, T)
        self._objects_gone(objects.finished)
        clock.lap("filtering")
        events = objects.events + l4.classify(t_ns)
        clock.lap("classification")

        image4 = l4.entity_image(seg.labels, objects.ids)
        in_object = l4.confirmed_pixels(image4)
        surfaces = self._level3(t_ns, px, seg, objects.ids, in_object, T)
        clock.lap("level3")
        image2 = self._level2(t_ns, px, image4, in_object, surfaces)
        self.ctx.sweep += 1  # counted after levels 3 and 2, whose rewrites ctx.due spreads
        clock.lap("level2")
        groups = self.level5.step(t_ns, image4, l4)
        events += groups.events
        clock.lap("groups")

        l4.unexplained(seg.labels, image4)
        images = {2: image2, 3: surfaces.image, 4: image4, 5: groups.image}
        result = self.results.make(
            t_ns, px, images, seg.ground, surfaces.surfaces, events, attention
        )
        clock.lap("images")
        result.timings_s = clock.laps
        return result

    def _objects_gone(self, finished: np.ndarray) -> None:
        """Objects that ended this sweep take their face (level 3) and lists (level 2)."""
        for oid in finished.tolist():
            self.level3.object_gone(oid)
            self.level2.owner_gone(oid)

    def _level3(
        self,
        t_ns: int,
        px: PixelsObserved,
        seg: Segments,
        object_ids: np.ndarray,
        in_object: np.ndarray,
        T_world_ladar: np.ndarray,
    ) -> SurfacesObserved:
        """Level 3 on level 4's segments (``object_ids`` (K,) their objects; ``in_object``
        (H, W) bool the confirmed objects' pixels): the ground, the confirmed objects' faces,
        the free surfaces."""
        return self.level3.step(
            t_ns, px.xyz_w, px.xyz_g, px.valid, seg.ground, seg.labels, seg.attributes,
            object_ids, self.level4.confirmed_ids(), in_object, T_world_ladar, px.row_el,
        )  # fmt: skip

    def _level2(
        self,
        t_ns: int,
        px: PixelsObserved,
        image4: np.ndarray,
        in_object: np.ndarray,
        surfaces: SurfacesObserved,
    ) -> np.ndarray:
        """The level-2 entity image (H, W) int64: the lists of each pixel's owner (its
        confirmed object, else its level-3 surface), overlaid by level 3's contact boundaries
        and creases."""
        image2 = np.full(px.valid.shape, -1, dtype=np.int64)
        if self.config.lists:
            owner = np.where(in_object, image4, surfaces.image)
            intensity = px.img.intensity[..., 0]
            image2 = self.level2.step(
                t_ns, owner, px.range_m, px.valid, intensity, surfaces.free_px
            ).image
        has_contact = surfaces.contact >= 0
        image2[has_contact] = surfaces.contact[has_contact]
        return image2

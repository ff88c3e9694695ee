"""What the SP levels of one processor share: configuration, class library and table, id
source, sweep count, and the observations of the sweep.

Reference 001, 4.5.6 (levels 2 to 5 of sensory processing), 4.4.4 (entity images and the
class images made from them), 4.2 (the world model alone writes the KD, SP's observations
included). :class:`SPConfig` holds every parameter of levels 2-5; an :class:`SPContext` is
built once per :class:`sp.pipeline.SensoryProcessor` and handed to each level module
(:mod:`sp.level2_lists` ... :mod:`sp.level5_groups`), which record their observations in it
(:mod:`sp.observations`); SP holds no knowledge database.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from kd_store import ClassLibrary, Level, Status
from sp.classify import ClassifyConfig
from sp.egosphere import EgosphereConfig
from sp.events import EventClass
from sp.ground import GroundConfig
from sp.ground_prior import GroundPriorConfig
from sp.groups import GroupConfig
from sp.images import ClassTable
from sp.lists import ListConfig
from sp.observations import EventObserved, NewEntity, Observation
from sp.reid import ReidConfig
from sp.segments import SegmentConfig
from sp.surfaces import SurfaceConfig
from sp.tracking import TrackerConfig, TrackStatus
from sp.windowing import WindowConfig

# the entity image of each SP level (its pixels hold frame ids, reference 001, 4.4.4)
IMAGE_NAMES = {2: "sp2_lists", 3: "sp3_surfaces", 4: "sp4_objects", 5: "sp5_groups"}
# a track's status (sp.tracking) as the KD's
KD_STATUS = {
    TrackStatus.HYPOTHESIZED: Status.HYPOTHESIZED,
    TrackStatus.CONFIRMED: Status.CONFIRMED,
    TrackStatus.DENIED: Status.DENIED,
    TrackStatus.GONE: Status.GONE,
}


@dataclass(frozen=True)
class SPConfig:
    """Every parameter of SP levels 2-5, with its default, in one place."""

    egosphere: EgosphereConfig = field(
        default_factory=lambda: EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1)
    )
    ground: GroundConfig = field(default_factory=GroundConfig)
    ground_prior: GroundPriorConfig = field(default_factory=GroundPriorConfig)
    segments: SegmentConfig = field(default_factory=SegmentConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    reid: ReidConfig = field(default_factory=ReidConfig)
    classify: ClassifyConfig = field(default_factory=ClassifyConfig)
    groups: GroupConfig = field(default_factory=GroupConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    birth_hits: int = 2  # a hypothesis gets a KD frame (and "appeared") after this many hits
    # classes whose bodies are fixed where they stand (and their kinds): an object of one is
    # reported at rest whatever its filter's velocity, which follows the seen centre of a
    # face sliding along itself as more of it comes into view (the aperture problem)
    fixed_classes: tuple[str, ...] = ("building", "wall", "tree")
    min_pixels_attended: int = 2  # smallest hypothesis inside an attention window
    max_object_range_m: float = 120.0  # farther segments are left ungrouped
    min_object_height_m: float = 0.5  # lower segments are ground (bumps, ruts, curbs)
    # an object stands out of the ground: from its foot it rises at least foot_object_deg
    # steep over foot_rise_m, or leans back (a bush's underside). A segment rising more
    # gently, in the median of at least foot_min_columns columns, continues the ground (a
    # bank or a mound steeper than the ground's slope limit) and goes back to it. Only
    # columns whose returns lie at most foot_chord_m apart count: a face is told from a
    # dome's receding top only with two steps or more over foot_rise_m (far out, the rows
    # lie too far apart and the segment stays an object)
    foot_object_deg: float = 60.0
    foot_rise_m: float = 0.4
    foot_min_columns: int = 3
    foot_chord_m: float = 0.25
    # a segment holding two tracked people's predicted places (each within split_near_m of
    # its returns, at least split_min_apart_m apart) is cut between them
    split_near_m: float = 0.4
    split_min_apart_m: float = 0.5
    # a narrow upright segment (at most gap_split_max_length_m x gap_split_max_width_m, at
    # least gap_split_min_height_m tall) whose returns leave a gap of gap_split_m along its
    # long axis is two objects (people side by side before either is tracked)
    gap_split_m: float = 0.25
    gap_split_max_length_m: float = 2.6
    gap_split_max_width_m: float = 0.9
    gap_split_min_height_m: float = 1.0
    # two confirmed vehicles at rest, both measured, whose positions lie within this (m) are
    # pieces of one (a car's end and its side, cut apart by the car parked beside it): a
    # vehicle is at least 1.5 m across, and two parked side by side stand a body apart
    merge_vehicle_within_m: float = 1.5
    # two confirmed buildings at rest, both measured, whose footprints come within this (m)
    # are faces of one (its front and its side seen at a grazing angle, which recedes too
    # fast along a row to join the front): buildings stand further apart
    merge_building_gap_m: float = 0.5
    reclassify_margin: float = 0.05  # score gain needed to change a confirmed class
    # ... on a view with at least this share of the returns of the best view that had the
    # class (or on views that keep preferring the new class: sp.level4_objects.ClassEvidence)
    reclassify_min_share: float = 0.5
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
    # a broad thin plane tilted less than this is ground ... : the steepest bank loose soil
    # stands at (its angle of repose, 30-45 degrees), as a ditch's side or a cut slope do;
    # the column walk (max_slope_deg) gives up on such banks past a step, this takes them back
    terrain_tilt_deg: float = 45.0
    terrain_breadth_m: float = 0.25  # ... when its points spread this far along its middle axis
    terrain_thick_m: float = 0.12  # ... and this little across its plane (std, m)
    terrain_max_height_m: float = 1.2  # ... and it rises less than this over the ground
    terrain_clearance_m: float = 0.3  # ... from no higher than this above it (a car's hood is)
    face_tilt_deg: float = 20.0  # a plane within this of vertical is a face (level 3) ...
    face_breadth_m: float = 0.3  # ... when its points spread this far along its middle axis
    face_thick_m: float = 0.15  # ... and this little across it (std, m)
    deskew_max_gap_s: float = 0.5  # no constant-velocity deskew over a longer gap between poses


class SPContext:
    """The state the levels share: the configuration, the class library and the class table
    the class images are made from (entity id -> index into ``class_names``), the id source,
    the sweep count that spreads the list and surface frame rewrites over sweeps (:meth:`due`),
    and the sweep's observations in the order they were made (:meth:`take_observations`).

    ``classes`` is the class library the world model keeps (it adds the specific classes it
    founds from SP's observations; SP reads it). ``new_id`` gives a fresh frame id for each
    new entity or event SP observes; the world model passes its KD's id source, so images,
    tracks and frames share the id."""

    def __init__(self, classes: ClassLibrary, new_id: Callable[[], int], config: SPConfig) -> None:
        self.classes = classes
        self.new_id = new_id
        self.config = config
        self.class_table = ClassTable()  # entity id -> class index, for the class images
        self.class_names: list[str] = []
        self.class_index: dict[str, int] = {}
        self.refresh_classes()
        self.sweep = 0  # sweeps processed (counted after level 2)
        self.observations: list[Observation] = []
        self._created: dict[int, NewEntity] = {}  # this sweep's new entities by id
        self.classes_founded = False  # a specific class was founded: refresh before classifying

    # ------------------------------------------------------------------ observations

    def new_entity(
        self,
        name: str,
        level: Level,
        images: tuple[str, ...],
        status: Status = Status.HYPOTHESIZED,
        confidence: float = 0.0,
        generic_classes: tuple[str, ...] = (),
    ) -> int:
        """Observe a new entity; returns its id (taken from the id source now)."""
        op = NewEntity(
            self.new_id(), name, level, images, status, confidence, tuple(generic_classes)
        )
        self._created[op.entity_id] = op
        self.observations.append(op)
        return op.entity_id

    def event(
        self,
        event_class: EventClass,
        t_ns: int,
        entity_ids: Sequence[int],
        level: int,
        confidence: float = 1.0,
    ) -> int:
        """Observe an instantaneous event involving ``entity_ids``; returns its id."""
        op = EventObserved(
            self.new_id(),
            event_class,
            int(t_ns),
            tuple(int(i) for i in entity_ids),
            int(level),
            float(confidence),
        )
        self.observations.append(op)
        return op.event_id

    def record(self, op: Observation) -> None:
        """Observe a change (a frame's fields, a state, a relation ...)."""
        self.observations.append(op)

    def created(self, frame_id: int) -> NewEntity | None:
        """The new-entity observation of ``frame_id`` made this sweep, if any."""
        return self._created.get(frame_id)

    def take_observations(self) -> list[Observation]:
        """The observations since the last call, in order; the next sweep starts afresh."""
        out, self.observations, self._created = self.observations, [], {}
        return out

    def refresh_classes(self) -> None:
        """Re-read the class names from the class library (a specific class was founded).
        ``class_names`` is replaced, not changed, so earlier results keep theirs."""
        self.class_names = [p.name for p in self.classes]
        self.class_index = {n: i for i, n in enumerate(self.class_names)}

    def set_class(self, entity_id: int, name: str | None) -> None:
        """Point ``entity_id``'s pixels in the class images at class ``name``."""
        self.class_table.set([entity_id], [self.class_index.get(name, -1) if name else -1])

    def set_classes(self, ids: np.ndarray, names: Iterable[str | None]) -> None:
        """Point entities ``ids`` (n,) at classes ``names`` (n; None: no class)."""
        self.class_table.set(ids, [self.class_index.get(n or "", -1) for n in names])

    def due(self, ids: np.ndarray) -> np.ndarray:
        """(n,) bool: frames rewritten this sweep. List and surface frames are rewritten in
        turn, each every ``kd_refresh_sweeps`` sweeps (the levels' tables and images hold
        the latest), so the KD writes per sweep stay a fixed share of the entities."""
        every = self.config.kd_refresh_sweeps
        return (ids % every) == (self.sweep % every)


def unit(x: float) -> float:
    """``x`` clipped to [0, 1] (a confidence)."""
    return float(min(max(x, 0.0), 1.0))


def row_step(row_el: np.ndarray) -> float:
    """Median elevation step (rad, > 0) between neighbouring rows of the egosphere, from the
    rows' elevations ``row_el`` (H,) rad (NaN where a row has no return); 1 degree when there
    are too few rows to tell."""
    ok = np.flatnonzero(np.isfinite(row_el))
    if ok.size < 2:
        return math.radians(1.0)
    d = -np.diff(row_el[ok]) / np.diff(ok)
    d = d[d > 0]
    return float(np.median(d)) if d.size else math.radians(1.0)

"""What one SP cycle hands the world model: :class:`SPResult`, and :class:`ResultMaker`, which
assembles it from the levels' entity images.

Reference 001, 4.4.4-4.4.5: the entity images of levels 2-5 (pixels holding frame ids, -1
none), the class images and value images derived from them (made lazily, :mod:`sp.images`),
and per valid pixel of the egosphere image its world point, object and class, which the node
fuses into its maps.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from sp.context import IMAGE_NAMES, SPContext
from sp.images import LazyImages, class_image, class_values, value_images
from sp.level1 import PixelsObserved
from sp.observations import Observation

__all__ = ["ResultMaker", "SPResult"]


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


class ResultMaker:
    """Assembles each cycle's :class:`SPResult` from the shared context's classes; keeps the
    value of every class (one table per value name) until a class is founded."""

    def __init__(self, ctx: SPContext) -> None:
        self.ctx = ctx
        self._values: tuple[int, dict[str, np.ndarray]] = (-1, {})  # (n classes, tables)

    def make(
        self,
        t_ns: int,
        pixels: PixelsObserved,
        entity_images: dict[int, np.ndarray],
        ground: np.ndarray,
        surfaces: list[int],
        events: list[int],
        attention: np.ndarray,
    ) -> SPResult:
        """The cycle's result: the entity images (level -> (H, W) int64), their class and
        value images, and per valid pixel of ``pixels`` its world point (of ``xyz_w``),
        object and class. ``ground`` (H, W) bool, ``attention`` (H, W) bool the windows."""
        img = pixels.img
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
            points_world=pixels.xyz_w.reshape(-1, 3)[flat].astype(np.float32),
            point_entity_ids=pe,
            point_class_ids=point_class,
            objects=[int(i) for i in np.unique(pe[pe >= 0])],
            events=events,
            timings_s={},
            point_pixel=flat.astype(np.int64),
            point_index=img.point_index[..., 0].reshape(-1)[flat].astype(np.int64),
            attention_mask=attention,
            class_names=self.ctx.class_names,
        )

    def failed(self, t_ns: int, observations: list[Observation]) -> SPResult:
        """The result of a sweep that failed: empty images and points, ``ok`` False, and
        what the levels observed before it failed."""
        H, W = self.ctx.config.egosphere.n_rows, self.ctx.config.egosphere.n_cols
        return SPResult(
            t_ns=t_ns,
            entity_images={k: np.full((H, W), -1, np.int64) for k in IMAGE_NAMES},
            ground_mask=np.zeros((H, W), bool),
            points_world=np.zeros((0, 3), np.float32),
            point_entity_ids=np.zeros(0, np.int64),
            point_class_ids=np.zeros(0, np.int32),
            objects=[],
            events=[],
            timings_s={},
            class_names=self.ctx.class_names,
            observations=observations,
            ok=False,
        )

    def _class_images(
        self, entity_images: dict[int, np.ndarray], flat: np.ndarray
    ) -> tuple[Mapping[int, np.ndarray], Mapping[str, np.ndarray], np.ndarray]:
        """Class images per level and value images of the level-4/3 composite, made when
        first asked for from this cycle's classes (a copy of the class table, so a class
        set later does not reach this cycle's images), and the class of each valid pixel
        ``flat`` in the composite (its object's, else its surface's)."""
        lut = self.ctx.class_table.lut.copy()
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
        names = self.ctx.class_names
        if self._values[0] != len(names):
            self._values = (len(names), class_values(self.ctx.classes, names))
        return self._values[1]

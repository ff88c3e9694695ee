"""Class images and value images, registered with the entity images (one per SP level).

Reference 001, 4.4.4 (Figure 21): "when an entity is classified, the pixels that are labeled
with the entity name can be assigned the class name of the entity class. This produces a set
of class images"; "cost/risk/worth values of entities can be assigned to the pixels contained
in the entity class image. This generates a set of value images". 4.4.5: a pixel not assigned
to an entity is background or unknown (here -1 in class images, NaN in value images).

Both are table look-ups over the whole image, made when first asked for (:class:`LazyImages`):
:class:`ClassTable` keeps a dense array from
entity id to class index (entity ids are small consecutive integers handed out by the KD), so
a class image is one gather; a value image is a second gather through the class library's
value of each class.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import TypeVar

import numpy as np

from core.errors import EngineError
from kd_store import ClassLibrary

VALUE_NAMES = ("cost", "risk", "worth_preserve")
K = TypeVar("K")


class ImageError(EngineError, ValueError):
    """An entity id or class index out of range; names it."""


class ClassTable:
    """Entity id -> class index (into the pipeline's ``class_names``), -1 unclassified."""

    def __init__(self) -> None:
        self.lut = np.full(64, -1, dtype=np.int32)

    def set(self, ids: Iterable[int] | np.ndarray, codes: Iterable[int] | np.ndarray) -> None:
        """Point entities ``ids`` at class indices ``codes`` (-1 to forget the class)."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        codes = np.asarray(codes, dtype=np.int32).reshape(-1)
        if ids.size == 0:
            return
        if ids.min() < 0:
            raise ImageError(f"entity id {int(ids.min())} is negative")
        need = int(ids.max()) + 1
        if need > self.lut.size:
            grown = np.full(max(need, 2 * self.lut.size), -1, dtype=np.int32)
            grown[: self.lut.size] = self.lut
            self.lut = grown
        self.lut[ids] = codes

    def get(self, entity_id: int) -> int:
        return int(self.lut[entity_id]) if 0 <= entity_id < self.lut.size else -1

    def image(self, entity_image: np.ndarray) -> np.ndarray:
        """(H, W) int32 class index of each pixel's entity, -1 where no entity or no class."""
        return class_image(self.lut, entity_image)


def class_image(lut: np.ndarray, entity_image: np.ndarray) -> np.ndarray:
    """Class index (int32, -1 none) of each entry of ``entity_image`` (any shape, int64 ids,
    -1 none) through ``lut`` (entity id -> class index, a :class:`ClassTable`'s table)."""
    e = entity_image
    inside = (e >= 0) & (e < lut.size)
    return np.where(inside, lut[np.where(inside, e, 0)], -1).astype(np.int32)


class LazyImages(Mapping[K, np.ndarray]):
    """A read-only mapping whose images are made on first access by ``make(key)`` and then
    kept: a cycle's class and value images cost nothing unless someone looks at them."""

    def __init__(self, keys: Iterable[K], make: Callable[[K], np.ndarray]) -> None:
        self._keys = tuple(keys)
        self._make = make
        self._made: dict[K, np.ndarray] = {}

    def __getitem__(self, key: K) -> np.ndarray:
        if key not in self._keys:
            raise KeyError(key)
        if key not in self._made:
            self._made[key] = self._make(key)
        return self._made[key]

    def __iter__(self) -> Iterator[K]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)


def class_values(
    library: ClassLibrary, class_names: Sequence[str], names: Sequence[str] = VALUE_NAMES
) -> dict[str, np.ndarray]:
    """Per value name, a (C + 1,) float32 table: the value of each class of ``class_names``
    (the class library's ``value`` field, 0 where the class leaves it unset), and NaN last,
    for the class index -1."""
    out = {}
    for n in names:
        v = [float(getattr(library.get(c).value, n)) for c in class_names]
        out[n] = np.array([*v, np.nan], dtype=np.float32)
    return out


def value_images(class_image: np.ndarray, tables: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """(H, W) float32 value image per name from a class image ((H, W) int32, -1 none) and the
    tables of :func:`class_values`; NaN where the pixel has no class."""
    out = {}
    for n, t in tables.items():
        if class_image.size and int(class_image.max(initial=-1)) >= t.size - 1:
            raise ImageError(
                f"class index {int(class_image.max())} beyond the {t.size - 1} classes"
            )
        out[n] = t[class_image]  # -1 takes the last entry: NaN
    return out

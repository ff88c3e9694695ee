"""Classification: normalised dot product of attribute vectors with the class prototypes.

Reference 001, 4.5.1 (classification: "the attributes of an entity are compared with the
attributes of class prototypes ... a normalised dot product"), 4.4.3 (generic and specific
classes; "a confirmed entity that matches no class ... becomes the prototype of a new specific
class").

The dot product is taken in a feature space where it can tell classes apart: each attribute
``a`` becomes ``f_a(x) = w_a * (log(x + eps_a) - mu_a)``, with ``mu_a`` the mean of the
level's prototypes (so a vector of sizes points towards "larger than usual" or "smaller than
usual" rather than always into the positive quadrant) and ``eps_a`` a floor that keeps zero
speeds finite. The score of class c is the cosine of the entity's and the prototype's features
over the attributes the prototype defines and the entity has, shrunk towards zero by the
distance between them (``score = cos * exp(-|f_e - f_c|^2 / (2 s^2))``), so that a vector in
the right direction but far off in scale (a hill-sized "bush") matches nothing well.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from kd_store import ClassKind, ClassLibrary, Level


class ClassifyError(ValueError):
    """A level with no prototypes or an attribute vector of the wrong kind; names it."""


EPS: dict[str, float] = {"speed_mps": 0.5, "roughness_m": 0.05, "count": 1.0}
DEFAULT_EPS = 0.1


@dataclass(frozen=True)
class ClassifyConfig:
    """match: best score below which a confirmed entity founds a new specific class;
    scale: the feature distance ``s`` at which the cosine is shrunk by exp(-1/2)."""

    match: float = 0.2
    scale: float = 1.5


@dataclass(frozen=True)
class Match:
    """Best class, its score in [-1, 1], its generic lineage (general to specific, without the
    geometric root) and the scores of every candidate class."""

    name: str | None
    score: float
    generic: tuple[str, ...]
    scores: Mapping[str, float]


class Classifier:
    """Generic classes of one SP level from a :class:`~kd_store.ClassLibrary`. A specific class
    is the prototype of one entity (4.4.3): the pipeline points that entity at it, it is not a
    candidate for others."""

    def __init__(
        self, library: ClassLibrary, level: Level | int, config: ClassifyConfig | None = None
    ) -> None:
        self.library = library
        self.level = Level(level)
        self.config = config or ClassifyConfig()
        self.refresh()

    def refresh(self) -> None:
        """Re-read the library (after a specific class was founded)."""
        self.protos = [
            p
            for p in self.library
            if p.level == self.level and p.kind == ClassKind.GENERIC and p.attributes
        ]
        names = sorted({a for p in self.protos for a in p.attributes})
        self.mu = {
            a: float(
                np.mean(
                    [
                        math.log(p.attributes[a] + EPS.get(a, DEFAULT_EPS))
                        for p in self.protos
                        if a in p.attributes
                    ]
                )
            )
            for a in names
        }
        self._feat = [
            {a: p.weights[a] * self._log(a, v) for a, v in p.attributes.items()}
            for p in self.protos
        ]

    def _log(self, a: str, v: float) -> float:
        return math.log(max(v, 0.0) + EPS.get(a, DEFAULT_EPS)) - self.mu[a]

    def classify(self, attributes: Mapping[str, float]) -> Match:
        """Best class for ``attributes`` (name -> value, units in the names; NaN = missing)."""
        scores: dict[str, float] = {}
        for p, fp in zip(self.protos, self._feat, strict=True):
            keys = [a for a in fp if a in attributes and math.isfinite(attributes[a])]
            if not keys:
                continue
            e = np.array([p.weights[a] * self._log(a, attributes[a]) for a in keys])
            c = np.array([fp[a] for a in keys])
            norm = float(np.linalg.norm(e) * np.linalg.norm(c))
            cos = float(e @ c) / norm if norm > 1e-12 else 0.0
            dist2 = float(np.sum((e - c) ** 2))
            scores[p.name] = cos * math.exp(-dist2 / (2 * self.config.scale**2))
        if not scores:
            return Match(None, 0.0, (), scores)
        best = max(scores, key=lambda k: scores[k])
        lineage = self.library.lineage(best)
        generic = tuple(
            n for n in reversed(lineage) if self.library.get(n).kind == ClassKind.GENERIC
        )
        return Match(best, scores[best], generic, scores)

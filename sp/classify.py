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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from kd_store import ClassKind, ClassLibrary, Level


class ClassifyError(ValueError):
    """A level with no prototypes or an attribute vector of the wrong kind; names it."""


EPS: dict[str, float] = {
    "speed_mps": 0.5,
    "roughness_m": 0.05,
    "count": 1.0,
    "edge_share": 0.05,
    "vertex_share": 0.05,
    "range_jump_m": 0.05,
    "contrast": 0.05,
    "reflectance": 0.05,
    "camera_intensity": 0.05,
}
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
        return self._match(scores)

    def classify_many(self, rows: Sequence[Mapping[str, float]]) -> list[Match]:
        """:meth:`classify` of every row at once (same scores to rounding): a features matrix
        (rows x attributes, NaN missing) against each prototype, so many entities cost a few
        array operations per prototype, not a Python loop per entity."""
        if not rows:
            return []
        names = sorted(self.mu)
        X = np.array([[float(r.get(a, math.nan)) for a in names] for r in rows], dtype=np.float64)
        eps = np.array([EPS.get(a, DEFAULT_EPS) for a in names])
        mu = np.array([self.mu[a] for a in names])
        with np.errstate(invalid="ignore"):
            F = np.log(np.maximum(X, 0.0) + eps) - mu  # NaN stays NaN: missing
        S = np.full((len(rows), len(self.protos)), np.nan)
        for j, (p, fp) in enumerate(zip(self.protos, self._feat, strict=True)):
            w = np.array([p.weights.get(a, 0.0) for a in names])
            c = np.array([fp.get(a, 0.0) for a in names])
            has = np.array([a in fp for a in names])
            use = np.isfinite(F) & has
            e = np.where(use, F * w, 0.0)
            cu = np.where(use, c, 0.0)
            norm = np.linalg.norm(e, axis=1) * np.linalg.norm(cu, axis=1)
            cos = np.where(norm > 1e-12, (e * cu).sum(axis=1) / np.maximum(norm, 1e-300), 0.0)
            dist2 = ((e - cu) ** 2).sum(axis=1)
            score = cos * np.exp(-dist2 / (2 * self.config.scale**2))
            S[:, j] = np.where(use.any(axis=1), score, np.nan)
        return [
            self._match(
                {p.name: float(S[i, j]) for j, p in enumerate(self.protos) if np.isfinite(S[i, j])}
            )
            for i in range(len(rows))
        ]

    def _match(self, scores: dict[str, float]) -> Match:
        if not scores:
            return Match(None, 0.0, (), scores)
        best = max(scores, key=lambda k: scores[k])
        lineage = self.library.lineage(best)
        generic = tuple(
            n for n in reversed(lineage) if self.library.get(n).kind == ClassKind.GENERIC
        )
        return Match(best, scores[best], generic, scores)

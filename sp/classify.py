"""Classification: attribute vectors against the class prototypes, by a normalised dot
product (written-down prototypes) or by a likelihood (prototypes fitted on training data).

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

What a real sensor shows of an object is not its prototype, and three rules say so:

* ``AT_MOST`` attributes (speed): the prototype is the most the class usually shows, so an
  entity below it (a parked car, a standing person) matches as well as one at it, and only
  one above it is penalised. Motion is evidence against a static class, stillness is no
  evidence against a mobile one.
* ``SEEN_FRACTION`` attributes (horizontal extents): a LADAR sees an object from one side, so
  its extents as seen run from this fraction of the prototype's full extent up to it (a car
  seen from its side is long and thin, from behind short); values in that band match the
  prototype, values below it are penalised from the band's lower end.
* ``PLAUSIBLE`` bounds: a class whose physical bounds an entity violates (a 3 m high "person",
  a 0.05 m thick one, a 0.3 m long "vehicle") is no candidate for it, whatever its score.

Extents alone do not tell a piece of a wall from a car's side, nor a tree crown from a car, nor
a standing person from a post, so objects also carry the shape of their points as a LADAR
sees them (``sp.level4_objects.SHAPE_KEYS``, averaged over the sweeps that saw a surface of points):
``verticality`` (|z| of the normal of the points' best plane: 0 for a wall, a building front,
a post or an upright person; a car's hood and roof face up), ``thickness_m`` (their spread
across that plane: a wall piece is a plane, a car a bent one, a crown a volume of leaves) and
``breadth_m`` (their spread along the middle axis: an upright person is narrow, at most a
0.9 m wide body's 0.26 m, where a wall piece of person height is as broad as it is long).
Neither tells a bush from a rock of its size, and a crown from a car's body only in part; the
texture of the points does (``roughness_m``, :func:`sp.computation.segment_roughness`,
averaged over the sweeps): leaves scatter a LADAR's returns in depth, a smooth body does not.
A dense hedge is nearly as smooth as a rock, and a far object shows too few returns for a
texture; where a colour camera sees the object, the excess green of its colour
(``camera_excess_green``, :mod:`sp.appearance`) tells leaves from stone.

Fitted prototypes (``ClassPrototype.fitted``: ``kd_store/classes_fitted.yaml``, made by
``wm.fit_classes`` from SP's own attributes of labelled tracks on training seeds) replace the
written-down ones of their level in the default library, since what a sensor shows of a class
(a person's head between two scan rows, a parked car's roof over the row in front) is learned
better than written down. Their values are the centres of the classes' ``log(x + eps)`` and
their weights one over its spread, so they are scored by that likelihood instead of the dot
product (:func:`_likelihood`). The ``AT_MOST`` rule holds for them too (the value is the most
the class usually showed), and so do the ``PLAUSIBLE`` bounds but for the lower bounds of the
extents, which partial views undercut and the fit has seen (a person's stay:
``WHOLE_EXTENTS``). The two kinds of score are not on one scale, so a level with fitted
prototypes classifies by those alone.

A fitted level may also carry a discriminant (``kd_store.Discriminant``, fitted by
``wm.fit_classes.fit_discriminant`` on the same training samples): a softmax over the fitted
classes of a linear function of the log attributes, their products and which are missing
(:func:`discriminant_features`). Where the level has one, it says which class an entity
most likely is (its probabilities are the scores, over the classes whose ``PLAUSIBLE`` bounds
the entity keeps), and the fitted prototype's likelihood only how well the entity matches
that class (``Match.fit``, which decides whether a specific class is founded). Each class's
own centre and spread, scored one attribute at a time, cannot draw the borders between
classes a sensor shows: a large tree's crown is thicker, more curved and wider than the
typical tree's, all evidence against "tree" for a likelihood narrower than the building's
(whose broad spread forgives everything), where the discriminant learns from the samples how
the attributes vary together within each class and where one class's samples give way to
another's. On development seeds 13-20 it names 0.89 of the labelled (track, sweep) samples
right against 0.77 for the likelihood.

The written-down rules and prototypes come from published typical dimensions (cars 3.5-5.5 m long,
1.5-2.1 m wide, 1.3-2.0 m high; persons 1.0-2.0 m high, 0.3-0.9 m wide; free-standing walls
10-25 m long, 0.4-0.6 m thick, 1.5-2.5 m high; street furniture, wheelie bins by EN 840 and
utility cabinets, 0.4-1.45 m across and 0.9-1.7 m high) and the shape of such bodies; the shape
prototypes were checked against (not fitted to) the simulator's development seeds 5 and 6
(scenarios default, parking, village), whose per-class medians they sit near. No real
recording was used to fit them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from core.errors import EngineError
from kd_store import ClassKind, ClassLibrary, ClassPrototype, Discriminant, Level
from sp.scene_prior import ScenePrior, adjust


class ClassifyError(EngineError, ValueError):
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
    "camera_excess_green": 0.05,
    # shape of an object's points (sp.level4_objects.SHAPE_KEYS): floors near a LADAR's range noise
    # (a few cm), so a plane's 0.005 m and 0.02 m thickness are both "planar"
    "thickness_m": 0.02,
    "breadth_m": 0.05,
    "verticality": 0.05,
}
DEFAULT_EPS = 0.1

# the prototype value is the most the class shows (see the module docstring)
AT_MOST: frozenset[str] = frozenset({"speed_mps"})
# extents as seen from one side span this fraction of the prototype's full extent up to it
SEEN_FRACTION: dict[str, float] = {"length_m": 0.35, "width_m": 0.3}
# ... unless the class overrides it: a free-standing wall (10-25 m long) is cut by occluders and
# the sensor's range and is seen in pieces of a metre or two
SEEN_FRACTION_OF: dict[str, dict[str, float]] = {"freestanding wall": {"length_m": 0.1}}
# physical bounds (lo, hi) per class and attribute (units in the names): outside them the class
# is no candidate.
# A person stands 1.0-2.1 m above the ground and is at least a torso thick (a pole or a sign
# post seen by a LADAR is a few centimetres across in its point cloud). Its tracked length
# reaches 2 m while it walks (the what-filter's box trails the moving body), but the points of
# one sweep spread along their middle (horizontal) axis no more than a 0.9 m wide body's
# standard deviation (0.9 / sqrt(12) = 0.26 m) and the range noise and swinging arms allow:
# a wider upright plane of person height is a piece of a wall or a fence, standing or not.
# A vehicle is at least 1.2 m across however it is seen and 0.9-4.5 m high.
PLAUSIBLE: dict[str, dict[str, tuple[float, float]]] = {
    "person": {
        "height_m": (1.0, 2.1),
        "length_m": (0.2, 2.0),
        "width_m": (0.12, 0.9),
        "breadth_m": (0.0, 0.35),
        "speed_mps": (0.0, 10.0),
    },
    "vehicle": {"height_m": (0.9, 4.5), "length_m": (1.2, 25.0), "speed_mps": (0.0, 60.0)},
    "post": {"length_m": (0.0, 1.2), "width_m": (0.0, 0.6), "speed_mps": (0.0, 0.5)},
    # a wall stands at least knee high (a kerb is ground) and does not move. (A long one seen
    # in part seems to slide along itself as more of it comes into view, the aperture problem;
    # allowing for that up to 3 m/s cost more moving cars and persons than it won walls on the
    # development seeds, so the bound stays that of a static object.)
    "freestanding wall": {"height_m": (0.5, 4.0), "speed_mps": (0.0, 0.5)},
    # bins, cabinets, machines: at most a 1100 l container's 1.45 x 1.1 m footprint or a tall
    # cabinet's 1.8 m, seen with a margin for the extents' error; they do not move
    "street furniture": {
        "height_m": (0.3, 2.2),
        "length_m": (0.0, 2.5),
        "width_m": (0.0, 1.8),
        "speed_mps": (0.0, 0.5),
    },
}


@dataclass(frozen=True)
class ClassifyConfig:
    """match: best ``Match.fit`` below which a confirmed entity founds a new specific class;
    scale: the feature distance ``s`` at which the cosine is shrunk by exp(-1/2);
    scene_prior_strength: a level with a discriminant that states its training prior
    exchanges that prior for the scene's as the run goes on (:mod:`sp.scene_prior`), with
    this many pseudo-objects of the training mix in the estimate, which rests on the latest
    ``scene_prior_window`` confirmed objects seen; None keeps the training prior."""

    match: float = 0.2
    scale: float = 1.5
    scene_prior_strength: float | None = 20.0
    scene_prior_window: int = 300


@dataclass(frozen=True)
class Match:
    """Best class, its score in [-1, 1], its generic lineage (general to specific, without the
    geometric root) and the scores of every candidate class. ``fit``: how well the entity
    matches the best class's prototype (the score itself, but for a level with a
    discriminant, whose probabilities say which class is likeliest and not whether any class
    is like the entity: there it is the fitted prototype's likelihood); below
    ``ClassifyConfig.match`` the entity matches no class well (4.4.3)."""

    name: str | None
    score: float
    generic: tuple[str, ...]
    scores: Mapping[str, float]
    fit: float


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
        # a likelihood and a dot product are no scores on one scale: a level with fitted
        # prototypes classifies by those alone
        if any(p.fitted for p in self.protos):
            self.protos = [p for p in self.protos if p.fitted]
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
        self.names = names
        self._fitted = _fitted_terms([p for p in self.protos if p.fitted], names)
        # a fitted discriminant of the level scores the classes it knows in place of their
        # prototypes (both fitted on the same training data; the discriminant learns where
        # one class ends and the next begins rather than each class's centre alone)
        self.disc = self.library.discriminants.get(self.level)
        if self.disc is not None:
            known = set(self.disc.classes)
            self.protos = [p for p in self.protos if p.name in known]

    def _log(self, a: str, v: float) -> float:
        return math.log(max(v, 0.0) + EPS.get(a, DEFAULT_EPS)) - self.mu[a]

    def classify(self, attributes: Mapping[str, float]) -> Match:
        """Best class for ``attributes`` (name -> value, units in the names; NaN = missing)."""
        return self.classify_many([attributes])[0]

    def classify_many(
        self,
        rows: Sequence[Mapping[str, float]],
        scene: ScenePrior | None = None,
        scene_ids: Sequence[int] | None = None,
    ) -> list[Match]:
        """:meth:`classify` of every row at once (same scores to rounding): a features matrix
        (rows x attributes, NaN missing) against each prototype, so many entities cost a few
        array operations per prototype, not a Python loop per entity.

        ``scene``: for a level with a discriminant, the scene prior (:mod:`sp.scene_prior`,
        over the discriminant's classes) the rows are classified under, updated first with
        the rows whose ``scene_ids`` (R,) are object ids (>= 0; -1: not a view to count)."""
        if not rows:
            return []
        if self.disc is not None:
            return self._classify_discriminant(rows, scene, scene_ids)
        names = self.names
        X = attribute_matrix(rows, names)
        L = log_features(X, names)
        F = L - np.array([self.mu[a] for a in names])
        S = np.full((len(rows), len(self.protos)), np.nan)
        for j, (p, fp) in enumerate(zip(self.protos, self._feat, strict=True)):
            if p.fitted:
                score, use = _likelihood(L, *self._fitted[p.name])
                ok = plausible(X, names, p.name, least_extents=p.name in WHOLE_EXTENTS)
                S[:, j] = np.where(use.any(axis=1), np.where(ok, score, IMPLAUSIBLE), np.nan)
                continue
            w = np.array([p.weights.get(a, 0.0) for a in names])
            c = np.array([fp.get(a, 0.0) for a in names])
            has = np.array([a in fp for a in names])
            use = np.isfinite(F) & has
            e = np.where(use, self._as_seen(F * w, c, w, names, p), 0.0)
            cu = np.where(use, c, 0.0)
            norm = np.linalg.norm(e, axis=1) * np.linalg.norm(cu, axis=1)
            cos = np.where(norm > 1e-12, (e * cu).sum(axis=1) / np.maximum(norm, 1e-300), 0.0)
            dist2 = ((e - cu) ** 2).sum(axis=1)
            score = cos * np.exp(-dist2 / (2 * self.config.scale**2))
            score = np.where(plausible(X, names, p.name), score, IMPLAUSIBLE)
            S[:, j] = np.where(use.any(axis=1), score, np.nan)
        return [
            self._match(
                {p.name: float(S[i, j]) for j, p in enumerate(self.protos) if np.isfinite(S[i, j])}
            )
            for i in range(len(rows))
        ]

    def _classify_discriminant(
        self,
        rows: Sequence[Mapping[str, float]],
        scene: ScenePrior | None,
        scene_ids: Sequence[int] | None,
    ) -> list[Match]:
        """:meth:`classify_many` by the level's :class:`~kd_store.Discriminant`: each class's
        probability given the attributes, over the classes whose ``PLAUSIBLE`` bounds the row
        keeps (the others score ``IMPLAUSIBLE``), under the scene's prior if given; a row with
        none of its attributes gets none."""
        disc = self.disc
        # the rows read once, over the prototypes' attributes and then the discriminant's
        cols = list(self.names) + [a for a in disc.attributes if a not in self.names]
        X = attribute_matrix(rows, cols)
        at = {a: j for j, a in enumerate(cols)}
        Xd = X[:, [at[a] for a in disc.attributes]]
        P = discriminant_probabilities(disc, Xd)
        ok = np.stack(
            [plausible(Xd, disc.attributes, c, least_extents=c in WHOLE_EXTENTS)
             for c in disc.classes], 1
        )  # fmt: skip
        P = np.where(ok, P, 0.0)
        P /= np.maximum(P.sum(axis=1, keepdims=True), 1e-300)
        if scene is not None:
            # this sweep's views update the scene's mix first, and are then classified under
            # it (the estimate and the decisions of one expectation maximisation)
            if scene.classes != disc.classes:
                raise ClassifyError(
                    f"scene prior over {scene.classes}, discriminant over {disc.classes}"
                )
            if scene_ids is not None:
                sid = np.asarray(scene_ids, dtype=np.int64)
                count = (sid >= 0) & np.isfinite(Xd).any(axis=1)
                scene.observe(sid[count].tolist(), P[count])
            P = adjust(P, scene.weights)
        names_p = [p.name for p in self.protos]
        col = {c: j for j, c in enumerate(disc.classes)}
        S = np.where(ok, P, IMPLAUSIBLE)[:, [col[n] for n in names_p]]
        seen = np.isfinite(Xd).any(axis=1)
        # how well the chosen class's fitted prototype matches: the discriminant cannot say
        # that an entity is like no class (a mound is still likeliest one of them); each row
        # against its own best class's likelihood terms, stacked (R', A), in one pass
        best = S.argmax(axis=1) if names_p else np.zeros(len(rows), dtype=int)
        # a class without a fitted prototype matches as well as it scores
        fit = S[np.arange(len(rows)), best] if names_p else np.zeros(len(rows))
        idx = [
            i for i in range(len(rows))
            if seen[i] and S[i, best[i]] > IMPLAUSIBLE and names_p[best[i]] in self._fitted
        ]  # fmt: skip
        if idx:
            F = log_features(X[idx, : len(self.names)], self.names)
            terms = [self._fitted[names_p[best[i]]] for i in idx]
            fit[idx] = _likelihood(F, *(np.stack([t[k] for t in terms]) for k in range(5)))[0]
        return [
            self._match(
                dict(zip(names_p, S[i].tolist(), strict=True)) if seen[i] else {}, float(fit[i])
            )
            for i in range(len(rows))
        ]

    def _as_seen(
        self,
        e: np.ndarray,
        c: np.ndarray,
        w: np.ndarray,
        names: Sequence[str],
        p: ClassPrototype,
    ) -> np.ndarray:
        """Entity features (R, A) moved onto the prototype's features ``c`` (A,) where the
        entity lies in the band the prototype accepts (``AT_MOST``, ``SEEN_FRACTION``); below
        the band they are shifted by its width, so the distance counts from its lower end."""
        out = e.copy()
        proto = p.attributes
        seen = SEEN_FRACTION | SEEN_FRACTION_OF.get(p.name, {})
        for i, a in enumerate(names):
            if a not in proto:
                continue
            if a in AT_MOST:
                lo = -np.inf
            elif a in seen:
                lo = w[i] * self._log(a, seen[a] * proto[a])
            else:
                continue
            col = e[:, i]
            inside = (col >= lo) & (col <= c[i])
            out[:, i] = np.where(inside, c[i], np.where(col < lo, col + (c[i] - lo), col))
        return out

    def _match(self, scores: dict[str, float], fit: float | None = None) -> Match:
        """The best of ``scores`` over the plausible classes; ``fit`` how well it matches
        (None: its score)."""
        candidates = {k: v for k, v in scores.items() if v > IMPLAUSIBLE}
        if not candidates:
            return Match(None, 0.0, (), scores, 0.0)
        best = max(candidates, key=lambda k: candidates[k])
        lineage = self.library.lineage(best)
        generic = tuple(
            n for n in reversed(lineage) if self.library.get(n).kind == ClassKind.GENERIC
        )
        return Match(best, scores[best], generic, scores, scores[best] if fit is None else fit)


def attribute_matrix(rows: Sequence[Mapping[str, float]], names: Sequence[str]) -> np.ndarray:
    """(R, A) float64 values of ``names`` in each row (name -> value); NaN where missing."""
    return np.array([[float(r.get(a, math.nan)) for a in names] for r in rows], dtype=np.float64)


def log_features(X: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """``log(x + eps_a)`` of attribute rows ``X`` (R, A) in ``names`` order, the space fitted
    classes live in (``EPS``; a negative value counts as 0, NaN stays NaN: missing)."""
    eps = np.array([EPS.get(a, DEFAULT_EPS) for a in names])
    with np.errstate(invalid="ignore"):
        return np.log(np.maximum(X, 0.0) + eps)


def discriminant_features(F: np.ndarray) -> np.ndarray:
    """Features (R, D) of a :class:`~kd_store.Discriminant` from centred log attributes ``F``
    (R, A), NaN missing: ``F`` with missing values at the centre (0), the missing indicators,
    the products ``F_i F_j`` (i <= j, row-major) and a 1; D = 2A + A(A+1)/2 + 1. The products
    let a linear softmax draw curved borders between classes (a crown thicker than usual
    because it is larger than usual is still a crown)."""
    miss = ~np.isfinite(F)
    F = np.where(miss, 0.0, F)
    i, j = np.triu_indices(F.shape[1])
    return np.hstack([F, miss.astype(np.float64), F[:, i] * F[:, j], np.ones((len(F), 1))])


def discriminant_probabilities(disc: Discriminant, X: np.ndarray) -> np.ndarray:
    """(R, C) probability of each of ``disc.classes`` for attribute rows ``X`` (R, A) in
    ``disc.attributes`` order (units in the names, NaN missing)."""
    eps = np.asarray(disc.eps)
    with np.errstate(invalid="ignore"):
        F = np.log(np.maximum(X, 0.0) + eps) - np.asarray(disc.centre)
    L = discriminant_features(F) @ np.asarray(disc.weights)
    L -= L.max(axis=1, keepdims=True)
    E = np.exp(L)
    return E / E.sum(axis=1, keepdims=True)


def _fitted_terms(
    protos: Sequence[ClassPrototype], names: Sequence[str]
) -> dict[str, tuple[np.ndarray, ...]]:
    """Per fitted prototype, over the attributes ``names``: which it has (A,) bool, which are
    ``AT_MOST`` (A,) bool, its centre ``log(value + eps)`` (A,), its weight ``1 / sd`` (A,)
    and ``log(sd / sd_ref)`` (A,), the spread judged against the typical spread of the fitted
    classes (their geometric mean), so a broad class pays for its breadth."""
    log_sd = {p.name: {a: -math.log(max(w, 1e-9)) for a, w in p.weights.items()} for p in protos}
    ref = {
        a: float(np.mean([sd[a] for sd in log_sd.values() if a in sd]))
        for a in {a for sd in log_sd.values() for a in sd}
    }
    at_most = np.array([a in AT_MOST for a in names])
    out = {}
    for p in protos:
        has = np.array([a in p.attributes for a in names])
        c = np.array(
            [math.log(max(p.attributes.get(a, 0.0), 0.0) + EPS.get(a, DEFAULT_EPS)) for a in names]
        )
        w = np.array([p.weights.get(a, 1.0) for a in names])
        spread = np.array([log_sd[p.name].get(a, 0.0) - ref.get(a, 0.0) for a in names])
        out[p.name] = (has, at_most, c, w, spread)
    return out


def _likelihood(
    F: np.ndarray,
    has: np.ndarray,
    at_most: np.ndarray,
    c: np.ndarray,
    w: np.ndarray,
    spread: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Score (R,) of a fitted prototype (its :func:`_fitted_terms`) for features ``F`` (R, A)
    = log(x + eps), and the attributes (R, A) it used:
    ``exp(-mean_a(rho(z_a) + log(sd_a / sd_ref_a)))`` over the attributes both have, with
    ``z_a`` the standardised distance from the class centre and ``rho`` Huber's loss
    (quadratic to ``HUBER_K``, linear beyond, so one odd attribute, such as a length cut
    short by an occluder, counts against a class but does not veto it). 1 at the centre of a
    class of typical spread; a geometric mean of likelihood ratios, so classes compare over
    the same attributes. An ``AT_MOST`` attribute counts only above the centre: stillness is
    no evidence against a mobile class, motion is evidence against a static one."""
    use = np.isfinite(F) & has
    d = np.where(use, F, 0.0) - c
    z = np.where(at_most, np.maximum(d, 0.0), np.abs(d)) * w
    rho = np.where(z <= HUBER_K, 0.5 * z**2, HUBER_K * z - 0.5 * HUBER_K**2)
    penalty = np.where(use, rho + spread, 0.0)
    return np.exp(-penalty.sum(axis=1) / np.maximum(use.sum(axis=1), 1)), use


EXTENTS = frozenset({"length_m", "width_m", "height_m"})  # what a partial view cuts short
# ... but not below a person's bounds: a low or thin blob called a person (a rock, a stump, a
# post's foot) is a phantom pedestrian every planner must steer around, where a real person
# seen in part is still an object to avoid (development seed 7 of the open world: without
# these bounds every rock was called a person)
WHOLE_EXTENTS = frozenset({"person"})
HUBER_K = 2.0  # standard deviations from a fitted class's centre where its penalty turns linear
IMPLAUSIBLE = -2.0  # the score of a class whose PLAUSIBLE bounds an entity violates


def plausible(
    X: np.ndarray, names: Sequence[str], cls: str, least_extents: bool = True
) -> np.ndarray:
    """(R,) bool: rows of ``X`` (R, len(names)) within class ``cls``'s PLAUSIBLE bounds (a
    missing value, NaN, violates nothing). Without ``least_extents`` the lower bounds of the
    extents (``EXTENTS``) are left out: a fitted class has seen how little of it a partial
    view shows (a parked car's roof over the row in front is 0.8 m high and 2 m long)."""
    ok = np.ones(X.shape[0], dtype=bool)
    for a, (lo, hi) in PLAUSIBLE.get(cls, {}).items():
        if not least_extents and a in EXTENTS:
            lo = -np.inf
        if a in names:
            x = X[:, list(names).index(a)]
            ok &= ~((x < lo) | (x > hi))
    return ok

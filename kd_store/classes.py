"""The class library: generic and specific prototypes with an ``is_a`` taxonomy (reference
001, section 4.4.3, classes of entities; prototype frames, Figure 20).

A prototype is a named attribute vector with a weight per attribute, at one SP level, with a
class value used by value judgment. Geometric classes (point, list, surface, object, group)
are the roots; generic classes hang below them; a specific class has exactly one member and
is founded from a confirmed entity that matched no generic class well.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from importlib import resources
from pathlib import Path

import yaml

from kd_store.errors import KDError
from kd_store.frames import VALUE_FIELDS, EntityFrame, Level, Status, Value


class ClassKind(StrEnum):
    GEOMETRIC = "geometric"
    GENERIC = "generic"
    SPECIFIC = "specific"


GEOMETRIC_ROOT: dict[int, str] = {1: "point", 2: "list", 3: "surface", 4: "object", 5: "group"}


@dataclass(frozen=True, slots=True)
class ClassPrototype:
    """One class: ``attributes`` name -> prototype value, ``weights`` name -> weight >= 0.

    ``fitted``: the prototype was fitted on labelled training data (``wm.fit_classes``): each
    value is the centre of the class's ``log(x + eps)`` and each weight one over its standard
    deviation, and the classifier scores it by that likelihood (``sp.classify``); otherwise
    the values are written down (catalogue dimensions) and scored by the normalised dot
    product of reference 001, 4.5.1."""

    name: str
    kind: ClassKind
    level: Level
    is_a: str | None = None
    attributes: Mapping[str, float] = field(default_factory=dict)
    weights: Mapping[str, float] = field(default_factory=dict)
    value: Value = field(default_factory=Value)
    fitted: bool = False


@dataclass(frozen=True)
class Discriminant:
    """A classifier of one SP level fitted on labelled training data (``wm.fit_classes``): a
    softmax over ``classes`` of a linear function of quadratic features of the attributes.

    ``attributes`` (A,) names; ``eps`` (A,) the floors of ``f = log(x + eps) - centre``;
    ``centre`` (A,) the training mean of ``log(x + eps)``; ``weights`` (D, C) with
    D = A (f) + A (f missing) + A (A + 1) / 2 (f_i f_j, i <= j, row-major) + 1 (bias) and C
    = len(classes). ``sp.classify.discriminant_probabilities`` evaluates it.

    ``prior`` (C,), summing to 1: the class shares the fit weighed its samples by (after its
    class balance), so the prior its probabilities carry; ``views`` (C,): the mean number of
    samples (views in sweeps) per training track of each class. None where the fit did not
    say (``sp.scene_prior`` then cannot exchange the prior for the scene's)."""

    level: Level
    attributes: tuple[str, ...]
    eps: tuple[float, ...]
    centre: tuple[float, ...]
    classes: tuple[str, ...]
    weights: tuple[tuple[float, ...], ...]
    prior: tuple[float, ...] | None = None
    views: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        a, c = len(self.attributes), len(self.classes)
        d = 2 * a + a * (a + 1) // 2 + 1
        if len(self.eps) != a or len(self.centre) != a:
            raise KDError(f"discriminant: {a} attributes but {len(self.eps)} eps, "
                          f"{len(self.centre)} centres")  # fmt: skip
        if len(self.weights) != d or any(len(r) != c for r in self.weights):
            raise KDError(
                f"discriminant: weights must be {d} rows of {c} (attributes {a}, classes {c})"
            )
        if not all(math.isfinite(v) for r in self.weights for v in r):
            raise KDError("discriminant: a weight is not finite")
        if self.prior is not None and (
            len(self.prior) != c
            or not all(math.isfinite(v) and v > 0 for v in self.prior)
            or abs(sum(self.prior) - 1.0) > 1e-3
        ):
            raise KDError(
                f"discriminant: prior {self.prior} is not {c} positive shares summing to 1"
            )
        if self.views is not None and (
            len(self.views) != c or not all(math.isfinite(v) and v >= 1 for v in self.views)
        ):
            raise KDError(f"discriminant: views {self.views} are not {c} counts of at least 1")


def descendants(is_a: Mapping[str, str | None], name: str) -> set[str]:
    """``name`` and every class whose ``is_a`` chain reaches it; ``is_a[c]`` is the parent of
    class ``c``, None for a root (every parent a key)."""
    out = set()
    for c in is_a:
        k: str | None = c
        while k is not None and k != name:
            k = is_a[k]
        if k == name:
            out.add(c)
    return out


class ClassLibrary:
    """Prototypes by name with the ``is_a`` taxonomy; insertion order is kept."""

    def __init__(self, prototypes: list[ClassPrototype] | None = None) -> None:
        self._by_name: dict[str, ClassPrototype] = {}
        self.dirty: set[str] = set()
        # level -> the classifier fitted on training data that replaces its prototypes' scores
        self.discriminants: dict[Level, Discriminant] = {}
        # counts the changes (:meth:`add`), so that a copy of the taxonomy taken in one cycle
        # can be kept for the next when nothing changed (wm.serve_copy.Taxonomy)
        self.version = 0
        for p in prototypes or []:
            self.add(p)
        self.dirty.clear()

    @classmethod
    def default(cls, fitted: bool = True) -> ClassLibrary:
        """The library shipped in ``kd_store/classes.yaml``, with the prototypes fitted on
        training data (``kd_store/classes_fitted.yaml``, made by ``wm.fit_classes``) in
        place of the written-down ones unless ``fitted`` is False."""
        text = resources.files("kd_store").joinpath("classes.yaml").read_text()
        lib = cls.from_yaml(text, "kd_store/classes.yaml")
        overlay = resources.files("kd_store").joinpath("classes_fitted.yaml")
        if fitted and overlay.is_file():
            lib.apply_fitted(overlay.read_text(), "kd_store/classes_fitted.yaml")
            lib.dirty.clear()
        return lib

    def apply_fitted(self, text: str, source: str | Path = "<yaml>") -> None:
        """Replace the attributes and weights of the classes named in a fitted overlay (the
        layout ``wm.fit_classes`` writes: ``classes: [{name, attributes: {a: [value,
        weight]}}]``) and mark them fitted; their kind, level, ``is_a`` and value stay. An
        overlay's ``discriminant`` (:class:`Discriminant`'s fields) becomes its level's; an
        overlay without one leaves the levels it fits none."""
        try:
            doc = yaml.safe_load(text)
            rows = doc["classes"]
            d = doc.get("discriminant")
            disc = None if not d else Discriminant(
                Level(int(d["level"])),
                tuple(map(str, d["attributes"])),
                tuple(map(float, d["eps"])),
                tuple(map(float, d["centre"])),
                tuple(map(str, d["classes"])),
                tuple(tuple(map(float, r)) for r in d["weights"]),
                None if d.get("prior") is None else tuple(map(float, d["prior"])),
                None if d.get("views") is None else tuple(map(float, d["views"])),
            )  # fmt: skip
            for c in disc.classes if disc else ():
                self.get(c)
            for row in rows:
                base = self.get(str(row["name"]))
                attrs = row["attributes"]
                fitted = ClassPrototype(
                    base.name, base.kind, base.level, base.is_a,
                    attributes={k: float(v[0]) for k, v in attrs.items()},
                    weights={k: float(v[1]) for k, v in attrs.items()},
                    value=base.value, fitted=True,
                )  # fmt: skip
                self.add(fitted)
            # a discriminant fitted with other prototypes of these levels no longer holds
            for level in {self.get(str(row["name"])).level for row in rows}:
                self.discriminants.pop(level, None)
            if disc is not None:
                self.discriminants[disc.level] = disc
        except (yaml.YAMLError, KeyError, TypeError, ValueError, IndexError, KDError) as e:
            raise KDError(f"fitted classes {source}: not a fitted-classes document ({e})") from None

    @classmethod
    def from_yaml(cls, text: str, source: str | Path = "<yaml>") -> ClassLibrary:
        """Parse the ``classes.yaml`` layout (see that file)."""
        try:
            doc = yaml.safe_load(text)
            rows = doc["classes"]
        except (yaml.YAMLError, KeyError, TypeError) as e:
            raise KDError(f"class library {source}: not a classes document ({e})") from None
        protos = []
        for row in rows:
            attrs = row.get("attributes") or {}
            try:
                protos.append(
                    ClassPrototype(
                        name=str(row["name"]),
                        kind=ClassKind(row["kind"]),
                        level=Level(int(row["level"])),
                        is_a=row.get("is_a"),
                        attributes={k: float(v[0]) for k, v in attrs.items()},
                        weights={k: float(v[1]) for k, v in attrs.items()},
                        value=Value(**{k: float(v) for k, v in (row.get("value") or {}).items()}),
                    )
                )
            except (KeyError, ValueError, TypeError, IndexError) as e:
                raise KDError(f"class library {source}: bad class {row!r} ({e})") from None
        return cls(protos)

    # ------------------------------------------------------------------ reading

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def __iter__(self) -> Iterator[ClassPrototype]:
        return iter(self._by_name.values())

    def __len__(self) -> int:
        return len(self._by_name)

    def get(self, name: str) -> ClassPrototype:
        try:
            return self._by_name[name]
        except KeyError:
            raise KDError(f"class {name!r} is not in the class library") from None

    def lineage(self, name: str) -> list[str]:
        """``name`` and its ``is_a`` ancestors, most specific first."""
        out = [self.get(name).name]
        while (parent := self._by_name[out[-1]].is_a) is not None:
            out.append(parent)
        return out

    def descendants(self, name: str) -> set[str]:
        """``name`` and every class whose lineage contains it."""
        self.get(name)
        return descendants({c: p.is_a for c, p in self._by_name.items()}, name)

    # ------------------------------------------------------------------ writing

    def add(self, p: ClassPrototype) -> None:
        """Add or replace a prototype; its ``is_a`` must exist and not make a cycle."""
        where = f"class {p.name!r}"
        if p.is_a is not None:
            if p.is_a not in self._by_name:
                raise KDError(f"{where}: is_a {p.is_a!r} is not in the class library")
            if p.name in self.lineage(p.is_a):
                raise KDError(f"{where}: is_a {p.is_a!r} would make an is_a cycle")
        if set(p.weights) != set(p.attributes):
            raise KDError(
                f"{where}: weights {sorted(p.weights)} != attributes {sorted(p.attributes)}"
            )
        for k, v in (*p.attributes.items(), *p.weights.items()):
            if not math.isfinite(v):
                raise KDError(f"{where}: attribute {k!r} has a non-finite value or weight {v!r}")
        if any(w < 0 for w in p.weights.values()):
            raise KDError(f"{where}: negative weight in {dict(p.weights)}")
        for k in VALUE_FIELDS:
            if not math.isfinite(getattr(p.value, k)):
                raise KDError(f"{where}: value {k} is not finite")
        self._by_name[p.name] = p
        self.dirty.add(p.name)
        self.version += 1

    def found_specific(self, entity: EntityFrame) -> ClassPrototype:
        """Found a specific class for a confirmed entity (4.4.3, specific entity classes): its
        prototype is the entity's estimated attributes (weight 1 each), ``is_a`` its most
        specific class or the geometric root of its level. Returns the new prototype; the
        caller points the entity at it."""
        if entity.status != Status.CONFIRMED:
            raise KDError(
                f"entity {entity.id} ({entity.name!r}): status {entity.status.value!r}; only a "
                "confirmed entity can found a specific class"
            )
        parent = entity.most_specific_class or GEOMETRIC_ROOT[int(entity.level)]
        if parent not in self._by_name:
            raise KDError(f"entity {entity.id}: class {parent!r} is not in the class library")
        attrs = {
            k: float(a.estimated)
            for k, a in entity.attributes.items()
            if math.isfinite(a.estimated)
        }
        proto = ClassPrototype(
            name=f"{entity.name}#{entity.id}",
            kind=ClassKind.SPECIFIC,
            level=Level(entity.level),
            is_a=parent,
            attributes=attrs,
            weights=dict.fromkeys(attrs, 1.0),
            value=entity.value,
        )
        self.add(proto)
        return proto

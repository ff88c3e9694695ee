"""Appearance in classification: an observed appearance attribute (LADAR reflectance, camera
intensity) counts; one never observed is left out, not read as zero. On the written-down
prototypes, which carry appearance (the fitted ones leave brightness out and use the camera's
excess green: wm.fit_classes)."""

from __future__ import annotations

import math

import pytest

import kd_store
from kd_store import ClassLibrary, Level
from kd_store.classes import ClassPrototype
from sp.classify import Classifier
from sp.pipeline import SPConfig
from wm.entities import KDSensoryProcessor

APPEARANCE = ("reflectance", "camera_intensity")


def _without_appearance(lib: ClassLibrary) -> ClassLibrary:
    out = []
    for p in lib:
        keep = {a: v for a, v in p.attributes.items() if a not in APPEARANCE}
        w = {a: v for a, v in p.weights.items() if a not in APPEARANCE}
        out.append(ClassPrototype(p.name, p.kind, p.level, p.is_a, keep, w, p.value))
    return ClassLibrary(out)


SIZES = {"height_m": 1.6, "width_m": 0.4, "length_m": 0.4, "speed_mps": 0.0}


def test_object_prototypes_carry_appearance() -> None:
    lib = ClassLibrary.default(fitted=False)
    for name in ("building", "tree", "bush", "rock", "post", "vehicle", "person"):
        a = lib.get(name).attributes
        assert all(0.0 < a[k] < 1.0 for k in APPEARANCE)  # reflectances


def test_missing_appearance_is_left_out_not_zero() -> None:
    lib = ClassLibrary.default(fitted=False)
    c = Classifier(lib, Level.OBJECT)
    bare = Classifier(_without_appearance(lib), Level.OBJECT)
    m, ref = c.classify(SIZES), bare.classify(SIZES)
    # without appearance observed, the scores are those of prototypes without it (mu of the
    # other attributes is the same, so the features are too)
    assert m.scores == pytest.approx(ref.scores, abs=1e-12)
    nan = c.classify(SIZES | {"reflectance": math.nan, "camera_intensity": math.nan})
    assert nan.scores == pytest.approx(ref.scores, abs=1e-12)
    zero = c.classify(SIZES | {"reflectance": 0.0})
    assert zero.scores != pytest.approx(ref.scores, abs=1e-6)  # a zero is an observation


def test_appearance_tips_a_size_ambiguous_object() -> None:
    c = Classifier(ClassLibrary.default(fitted=False), Level.OBJECT)
    bright = c.classify(SIZES | {"reflectance": 0.8, "camera_intensity": 0.7})
    dark = c.classify(SIZES | {"reflectance": 0.2, "camera_intensity": 0.15})
    assert (
        bright.scores["post"] - bright.scores["person"]
        > dark.scores["post"] - dark.scores["person"]
    )


def test_pipeline_passes_only_observed_appearance() -> None:
    kd = kd_store.open(":memory:")
    sp = KDSensoryProcessor(kd, SPConfig(intensity_per_reflectance=200.0))
    assert sp.level4.appearance_of(5) == {}
    sp.level4.observe_appearance(sp.level4.track_reflectance, 5, 100.0)
    sp.level4.observe_appearance(sp.level4.track_reflectance, 5, 140.0)  # running mean, gain 0.3
    sp.level4.observe_appearance(sp.level4.track_reflectance, 5, math.nan)  # ignored
    assert sp.level4.appearance_of(5) == {"reflectance": pytest.approx(112.0 / 200.0)}
    sp.level4.observe_appearance(sp.level4.track_camera, 5, 0.25)
    assert sp.level4.appearance_of(5)["camera_intensity"] == 0.25
    off = KDSensoryProcessor(kd_store.open(":memory:"), SPConfig(appearance_classes=False))
    off.level4.observe_appearance(off.level4.track_camera, 5, 0.25)
    assert off.level4.appearance_of(5) == {}
    unknown = KDSensoryProcessor(kd_store.open(":memory:"))  # LADAR units unknown: camera only
    unknown.level4.observe_appearance(unknown.level4.track_reflectance, 5, 100.0)
    unknown.level4.observe_appearance(unknown.level4.track_camera, 5, 0.25)
    assert unknown.level4.appearance_of(5) == {"camera_intensity": 0.25}


def test_the_fitted_classes_tell_green_leaves_from_grey_stone() -> None:
    """The shipped library, fitted on training seeds: an object halfway between the fitted
    bush and rock in every attribute of size, shape and texture (the centre of the two in the
    classifier's log feature space) is named by the colour the camera saw: a bush when green,
    a rock when grey. Brightness does not move it."""
    from sp.classify import DEFAULT_EPS, EPS

    lib = ClassLibrary.default()
    bush, rock = lib.get("bush"), lib.get("rock")
    assert bush.fitted and rock.fitted
    mid = {}
    for a in set(bush.attributes) & set(rock.attributes) - {"camera_excess_green"}:
        eps = EPS.get(a, DEFAULT_EPS)
        mid[a] = math.sqrt((bush.attributes[a] + eps) * (rock.attributes[a] + eps)) - eps
    c = Classifier(lib, Level.OBJECT)
    leaves = c.classify(mid | {"camera_excess_green": 0.4})
    stone = c.classify(mid | {"camera_excess_green": 0.0})
    assert leaves.name == "bush" and stone.name == "rock"
    # the colour, not a lean of the other attributes, decides: it moves the scores well
    # past where they stand for the object the camera did not see
    unseen = c.classify(mid).scores
    assert stone.scores["rock"] > unseen["rock"] + 0.3
    assert leaves.scores["bush"] > unseen["bush"] + 0.1
    for grey in (0.05, 0.6):  # dark or bright, the same class
        seen = mid | {"camera_excess_green": 0.4, "camera_intensity": grey}
        assert c.classify(seen).name == "bush"

"""The scene prior (sp.scene_prior): the class shares of the scene in view, estimated from the
classifier's own posteriors, and what exchanging the training prior for them does."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kd_store import ClassLibrary, KDError, Level
from sp.classify import IMPLAUSIBLE, Classifier
from sp.scene_prior import ScenePrior, ScenePriorError, adjust
from wm.fit_classes import FitError, Samples, fit, fit_discriminant, to_yaml, training_prior

# two classes of one attribute, each a unit normal around its mean (the Bayes posterior under
# any prior is then known in closed form, not through the code under test)
MEANS = np.array([0.0, 2.0])


def _posterior(x: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """(R, 2) exact p(c | x) for unit normals around MEANS under ``prior``."""
    like = np.exp(-0.5 * (x[:, None] - MEANS[None, :]) ** 2)
    post = like * prior
    return post / post.sum(axis=1, keepdims=True)


def _scene(
    n_objects: int, shares: np.ndarray, views: tuple[int, int], seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Objects drawn with class ``shares``, each seen ``views[class]`` times: per view its
    object id, its attribute and its object's class (each (V,))."""
    rng = np.random.default_rng(seed)
    y = rng.choice(2, size=n_objects, p=shares)
    ids = np.repeat(np.arange(n_objects), np.array(views)[y])
    cls = y[ids]
    return ids, MEANS[cls] + rng.standard_normal(len(ids)), cls


@pytest.mark.parametrize("shares", [(0.9, 0.1), (0.15, 0.85)])
def test_the_estimate_finds_the_scene_mix_and_names_more_views_right(shares) -> None:
    # trained on a view mix of one half each; class "a" objects are seen in 4 views, "b" in 2
    pi_t = np.array([0.5, 0.5])
    views = (4, 2)
    ids, x, y = _scene(1200, np.array(shares), views, seed=7)
    prior = ScenePrior(("a", "b"), pi_t, views, strength=20.0, window=300)
    right_adjusted = right_trained = n_scored = 0
    for k in range(0, len(x), 30):  # a sweep of 30 views at a time
        P_t = _posterior(x[k : k + 30], pi_t)
        P_s = adjust(P_t, prior.weights)
        prior.observe(ids[k : k + 30], P_t)
        if ids[k] >= 600:  # once the estimate has settled
            right_adjusted += int((P_s.argmax(axis=1) == y[k : k + 30]).sum())
            right_trained += int((P_t.argmax(axis=1) == y[k : k + 30]).sum())
            n_scored += len(P_t[:30])
    assert prior.n_objects == 300
    # the estimate is the maximum a posteriori object mix of the 300 latest objects, each
    # known by its latest view, under the 20 pseudo-objects of the training mix ...
    held = np.array([k for k in range(len(y)) if k == len(ids) - 1 or ids[k] != ids[k + 1]])
    held = held[-300:]
    L = _posterior(x[held], pi_t) / pi_t
    assert np.allclose(prior.rho, _map_shares(L, 20.0 * prior.rho_t), atol=0.01)
    # ... which lies between the training mix and the true shares of those objects, much
    # nearer the truth (the overlap of the classes lets the pseudo-objects pull it back)
    truth = np.bincount(y[held], minlength=2) / 300
    assert np.all(np.abs(prior.rho - truth) < 0.3 * np.abs(prior.rho_t - truth))
    # Bayes' rule under the scene's view prior names more views right than under the
    # training prior, and nearly as many as the true scene prior does
    pi_s = np.array(shares) * views / np.dot(shares, views)
    bayes = float(np.mean(_posterior(x, pi_s).argmax(axis=1) == y))
    assert right_adjusted / n_scored > right_trained / n_scored + 0.01
    assert right_adjusted / n_scored > bayes - 0.02


def _map_shares(L: np.ndarray, pseudo: np.ndarray) -> np.ndarray:
    """The class shares maximising sum_i log(sum_c rho_c L_ic) + sum_c pseudo_c log rho_c,
    by a general optimiser over the simplex (softmax parameters)."""
    from scipy.optimize import minimize

    def cost(z: np.ndarray) -> float:
        rho = np.exp(z - z.max())
        rho /= rho.sum()
        return -float(np.log(L @ rho).sum() + pseudo @ np.log(rho))

    z = minimize(cost, np.zeros(L.shape[1]), method="Nelder-Mead", options={"xatol": 1e-8}).x
    rho = np.exp(z - z.max())
    return rho / rho.sum()


def test_a_scene_like_the_training_mix_keeps_its_posteriors() -> None:
    # a training view mix of 0.7 / 0.3 from objects seen 2 and 3 times: object shares 7:2
    pi_t = np.array([0.7, 0.3])
    ids, x, _ = _scene(1500, np.array([7 / 9, 2 / 9]), (2, 3), seed=3)
    prior = ScenePrior(("a", "b"), pi_t, (2, 3), strength=20.0, window=1000)
    for k in range(0, len(x), 40):
        prior.observe(ids[k : k + 40], _posterior(x[k : k + 40], pi_t))
    # (leaving out the views per object moves them to 1.07 and 0.84 here)
    assert np.allclose(prior.weights, 1.0, atol=0.12)


def test_the_estimate_starts_at_the_training_mix_and_counts_objects_not_views() -> None:
    prior = ScenePrior(("a", "b", "c"), (0.2, 0.3, 0.5), (1, 1, 1), strength=10.0)
    assert np.allclose(prior.weights, 1.0)
    # ten objects of "a", each seen in ten sweeps: ten objects against ten pseudo-objects
    # (the estimate counts each object once)
    for _ in range(10):
        prior.observe(list(range(10)), np.array([[1.0, 0.0, 0.0]] * 10))
    assert prior.n_objects == 10 and np.allclose(prior.rho, [0.6, 0.15, 0.25])
    # a view no class was plausible for (all zero) adds no object
    prior.observe([99], np.zeros((1, 3)))
    assert prior.n_objects == 10 and np.allclose(prior.rho, [0.6, 0.15, 0.25])


def test_the_window_forgets_the_objects_seen_longest_ago() -> None:
    prior = ScenePrior(("a", "b"), (0.5, 0.5), (1, 1), strength=1.0, window=5)
    prior.observe(list(range(5)), np.array([[1.0, 0.0]] * 5))
    assert np.allclose(prior.rho, [5.5 / 6, 0.5 / 6])
    # object 0 is seen again, now looking like a "b", then four new objects of "b" take the
    # slots of objects 1-4, not its (by first sighting, 4 would stay and 0 go: 1.5 / 6 "a")
    prior.observe([0], np.array([[0.0, 1.0]]))
    prior.observe(list(range(5, 9)), np.array([[0.0, 1.0]] * 4))
    assert prior.n_objects == 5 and np.allclose(prior.rho, [0.5 / 6, 5.5 / 6])


def test_adjusting_moves_probability_towards_the_likelier_class_and_keeps_zeros() -> None:
    P = np.array([[0.5, 0.5, 0.0], [0.0, 0.0, 0.0]])
    Q = adjust(P, np.array([3.0, 1.0, 10.0]))
    assert np.allclose(Q[0], [0.75, 0.25, 0.0]) and np.all(Q[1] == 0)


@pytest.mark.parametrize(
    ("classes", "pi", "views", "strength", "match"),
    [
        (("a", "b"), (0.5, 0.6), (1, 1), 10.0, "summing to 1"),
        (("a", "b"), (1.0, 0.0), (1, 1), 10.0, "positive"),
        (("a", "b", "c"), (0.5, 0.5), (1, 1, 1), 10.0, "3 positive"),
        (("a", "b"), (0.5, 0.5), (1, 0.5), 10.0, r"views per object \[1.0, 0.5\]"),
        (("a", "b"), (0.5, 0.5), (1, 1), 0.0, "strength 0.0"),
    ],
)
def test_a_prior_it_cannot_use_is_refused(classes, pi, views, strength, match) -> None:
    with pytest.raises(ScenePriorError, match=match):
        ScenePrior(classes, pi, views, strength)


def test_posteriors_that_are_not_probabilities_are_refused() -> None:
    prior = ScenePrior(("a", "b"), (0.5, 0.5), (1, 1), 10.0)
    with pytest.raises(ScenePriorError, match=r"shape \(2, 3\) for 2 views of 2 classes"):
        prior.observe([1, 2], np.full((2, 3), 1 / 3))
    with pytest.raises(ScenePriorError, match="summing to 1"):
        prior.observe([1], np.array([[0.7, 0.7]]))
    with pytest.raises(ScenePriorError, match="finite"):
        prior.observe([1], np.array([[math.nan, 1.0]]))


# ------------------------------------------------------------------ the fitted discriminant


def _two_classes(n_vehicle: int, n_person: int, seed: int) -> Samples:
    """Vehicles and persons by height alone, overlapping (1.5 and 1.7 m, 10 % spread)."""
    rng = np.random.default_rng(seed)
    s = Samples([], [], [])
    for cls, centre, n in (("vehicle", 1.5, n_vehicle), ("person", 1.7, n_person)):
        h = np.exp(np.log(centre + 0.1) + 0.1 * rng.standard_normal(n)) - 0.1
        s.rows += [{"height_m": float(v), "length_m": 1.0, "width_m": 0.5} for v in h]
        s.labels += [cls] * n
        s.tracks += [("log", i) for i in range(n)]
    return s


def test_the_discriminant_states_the_prior_its_probabilities_carry() -> None:
    s = _two_classes(4000, 500, 1)
    attributes = ["height_m"]
    disc = fit_discriminant(s, attributes, ["person", "vehicle"], balance=0.75)
    # the balance weighs each sample count ** -0.75, so the classes weigh count ** 0.25
    share = np.array([500, 4000], float) ** 0.25
    assert np.allclose(disc.prior, share / share.sum(), atol=1e-9)
    # every track of _two_classes is one sample
    assert disc.views == (1.0, 1.0)
    # ... and the fit's probabilities, weighed as it weighed its samples, average to those
    # shares (the score equation of the unpenalised biases)
    from sp.classify import attribute_matrix, discriminant_probabilities

    P = discriminant_probabilities(disc, attribute_matrix(s.rows, attributes))
    w = np.array([{"person": 500, "vehicle": 4000}[c] ** -0.75 for c in s.labels])
    assert np.allclose((P * w[:, None]).sum(axis=0) / w.sum(), disc.prior, atol=2e-3)
    assert training_prior(np.array([1.0, 1.0]), 0.3) == (0.5, 0.5)
    # a class asked for without samples has no share to state
    with pytest.raises(FitError, match=r"classes \['rock'\] have no samples"):
        fit_discriminant(s, attributes, ["person", "rock", "vehicle"])


def test_the_prior_survives_the_overlay_and_a_bad_one_is_refused() -> None:
    import yaml

    s = _two_classes(800, 400, 2)
    attributes = ["height_m", "length_m", "width_m"]
    text = to_yaml(fit(s, attributes), {}, fit_discriminant(s, attributes))
    lib = ClassLibrary.default(fitted=False)
    lib.apply_fitted(text)
    disc = lib.discriminants[Level.OBJECT]
    assert disc.prior is not None and math.isclose(sum(disc.prior), 1.0)
    assert disc.views == (1.0, 1.0)
    doc = yaml.safe_load(text)
    doc["discriminant"]["prior"] = [0.9, 0.9]
    with pytest.raises(KDError, match=r"prior \(0.9, 0.9\) is not 2 positive shares"):
        ClassLibrary.default(fitted=False).apply_fitted(yaml.safe_dump(doc))


def test_the_classifier_takes_the_scene_prior_but_never_an_implausible_class() -> None:
    s = _two_classes(2000, 2000, 3)
    attributes = ["height_m", "length_m", "width_m"]
    lib = ClassLibrary.default(fitted=False)
    fitted = fit(s, attributes)
    lib.apply_fitted(to_yaml(fitted, {}, fit_discriminant(s, attributes)))
    clf = Classifier(lib, Level.OBJECT)
    between = {"height_m": 1.6, "length_m": 1.0, "width_m": 0.5}
    disc = lib.discriminants[Level.OBJECT]
    before = clf.classify(between)
    # a scene of forty objects that all look like the other class
    other = {"height_m": 1.35 if before.name == "person" else 1.9, "length_m": 1.0, "width_m": 0.5}
    scene = ScenePrior(disc.classes, disc.prior, disc.views, strength=20.0)
    after = clf.classify_many([between, *[other] * 40], scene, [-1, *range(40)])[0]
    assert scene.n_objects == 40 and after.name != before.name
    # 2.5 m tall: no person, however many persons the scene holds
    persons = ScenePrior(disc.classes, disc.prior, disc.views, strength=1.0)
    persons.rho = np.where(np.array(disc.classes) == "person", 0.999, 0.001)
    tall = clf.classify_many([{"height_m": 2.5, "length_m": 1.0, "width_m": 0.5}], persons)[0]
    assert tall.scores["person"] == IMPLAUSIBLE and tall.name == "vehicle"


# ------------------------------------------------------------------ in a run


def test_a_run_learns_the_mix_of_its_scene_from_the_objects_it_confirmed(tmp_path) -> None:
    """A parking lot is mostly parked cars: the mix a run estimates there gives vehicles more
    than the training mix did, and rests on the confirmed objects it measured, each once."""
    import dataclasses

    from fixtures.simulate import simulate_to_log
    from kd_store import Status
    from wm.config import NodeConfig, PoseSource
    from wm.engine_config import EngineConfig
    from wm.run import run_node

    path = tmp_path / "parking.mcap"
    simulate_to_log("parking", path, seconds=4.0, seed=7, progress=False)
    node = run_node(path, ":memory:", NodeConfig(pose_source=PoseSource.TRUTH))
    try:
        scene = node.sp.level4.scene_prior
        confirmed = [
            f for f in node.kd.entities() if f.level == Level.OBJECT and f.status in
            (Status.CONFIRMED, Status.GONE)
        ]  # fmt: skip
        assert 0.8 * len(confirmed) <= scene.n_objects <= len(confirmed)
        vehicle = scene.classes.index("vehicle")
        assert scene.rho[vehicle] > scene.rho_t[vehicle] + 0.1
        assert int(np.argmax(scene.weights)) == vehicle
    finally:
        node.kd.close()
    # switched off, the run keeps the training mix
    cfg = EngineConfig(node=NodeConfig(pose_source=PoseSource.TRUTH))
    sp = dataclasses.replace(
        cfg.sp, classify=dataclasses.replace(cfg.sp.classify, scene_prior_strength=None)
    )
    node = run_node(path, ":memory:", dataclasses.replace(cfg, sp=sp), seconds=1.0)
    try:
        assert node.sp.level4.scene_prior is None
    finally:
        node.kd.close()

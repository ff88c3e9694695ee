"""Fit the level-4 class prototypes on training logs (reference 001, 4.4.3 prototypes;
4.5.1 classification), so that what a class looks like to the sensor is learned from data
rather than written down from catalogue dimensions.

What a LADAR shows of an object is not its catalogue shape: a car seen from behind is short,
a wall is seen in pieces, a bush's points are a shell of leaves. The attributes SP classifies by
(:meth:`sp.level4_objects.ObjectLevel.class_rows`: extents, evident speed and the shape of the
points) are therefore collected as SP computes them, per framed track and sweep, on logs with
ground truth, labelled with the class of the true box the track's centre lies in, and each
class's prototype becomes the centre and spread of its attributes in the classifier's feature
space (``log(x + eps)``): the value ``exp(mean) - eps`` and the weight ``1 / std``. On the
same samples :func:`fit_discriminant` fits the softmax (``kd_store.Discriminant``) by which
:class:`sp.classify.Classifier` chooses among the fitted classes; each prototype's likelihood
then says how well the chosen class matches.

The samples depend a little on the classes in use while they are collected (level 4's person
and vehicle tracks), so a refit after the classifier changed moves the prototypes slightly
(the shipped file is this command's output with the classifier it ships with).

The split (docs/evaluation.md): prototypes are fitted on development seeds only
(``TRAINING_SETS``), never on the evaluation seeds; ``python -m wm.fit_classes`` refuses an
evaluation seed. Brightness (LADAR reflectance, camera grey) is left out by default: it
depends on a sensor's calibration, and a prototype fitted to one sensor's intensity scale
would not carry over to another's. The camera's excess green (``camera_excess_green``,
:mod:`sp.appearance`) is fitted: a ratio of colour channels, it is the same under any exposure
or gain, and it is what tells leaves from stone where the points alone do not (a bush and a rock
of one size and roughness). An object the camera never saw lacks it and is classified without.

Usage::

    python -m wm.fit_classes --cache DIR             # the shipped TRAINING_SETS
    python -m wm.fit_classes --scenarios open --seeds 40 41 ... --out my_classes.yaml
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections import defaultdict
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from core.errors import EngineError
from kd_store import Discriminant
from logs.types import ObjectBoxes

log = logging.getLogger(__name__)

#: development seeds the shipped prototypes were fitted on, per scenario (docs/evaluation.md,
#: the split). Rocks and bushes stand only in the default and open worlds, and 16 logs of each
#: held about 25 tracks of either, against thousands of vehicles and buildings, so those two
#: worlds get three times the seeds.
TRAINING_SETS: dict[str, tuple[int, ...]] = {
    "default": tuple(range(40, 88)),
    "village": tuple(range(40, 56)),
    "open": tuple(range(40, 88)),
    "parking": tuple(range(40, 56)),
}
TRAINING_SCENARIOS: tuple[str, ...] = tuple(TRAINING_SETS)
TRAINING_SEEDS: tuple[int, ...] = tuple(sorted(set().union(*TRAINING_SETS.values())))
#: attributes fitted by default: geometry, motion, the shape of the points, their texture and
#: their colour's excess green (not their brightness)
FIT_ATTRIBUTES: tuple[str, ...] = (
    "height_m", "width_m", "length_m", "speed_mps", "thickness_m", "curvature",
    "verticality", "breadth_m", "clearance_m", "longest_m", "roughness_m", "camera_excess_green",
)  # fmt: skip
#: attributes some sensor suites never give (no colour camera), and the camera gives only for
#: the objects it happens to see: the discriminant is also fitted on a copy of every sample
#: without them (:func:`fit_discriminant`)
OPTIONAL_ATTRIBUTES: tuple[str, ...] = ("camera_excess_green",)
#: the simulator's true classes -> the library's level-4 classes
TRUE_TO_LIBRARY: dict[str, str] = {"wall": "freestanding wall"}
MIN_STD = 0.05  # floor of a fitted spread (log units): a class never seen to vary still may
LABEL_DISTANCE_M = 0.3  # a track's centre this close to a true box's footprint takes its class
MIN_SAMPLES = 30  # a class (or a mode) with fewer (track, sweep) samples is not fitted
USUAL_MOST = 90  # percentile an AT_MOST attribute's prototype value is taken at
#: the discriminant weighs each class's samples by count ** -CLASS_BALANCE: 0 lets the many
#: vehicle and building samples drown rocks and bushes, 1 gives every class the same say
CLASS_BALANCE = 0.75
L2 = 1e-4  # ridge on the discriminant's weights (not its biases), per unit of sample weight
MAX_ITER = 1000  # L-BFGS iterations of the discriminant's fit


class FitError(EngineError):
    """Training logs without truth, an evaluation seed asked for, or too few samples."""


@dataclass
class Samples:
    """Labelled attribute rows: ``rows[i]`` (attribute -> value) of a track whose centre lay
    in a true box of class ``labels[i]``; ``tracks[i]`` the (log, track id) it came from."""

    rows: list[dict[str, float]]
    labels: list[str]
    tracks: list[tuple[str, int]]

    def __len__(self) -> int:
        return len(self.labels)

    def extend(self, other: Samples) -> None:
        self.rows += other.rows
        self.labels += other.labels
        self.tracks += other.tracks


def label_tracks(xy: np.ndarray, boxes: ObjectBoxes) -> list[str | None]:
    """Class of the true box (world frame) each track centre ``xy`` (K, 2) m lies in (within
    ``LABEL_DISTANCE_M`` of its footprint; None for none, or for two boxes of other classes)."""
    from core.geometry import footprint_distance
    from wm.truth import CLASS_ALIASES

    if len(boxes) == 0 or len(xy) == 0:
        return [None] * len(xy)
    d = footprint_distance(xy, boxes.centers[:, :2], boxes.sizes[:, :2], boxes.yaws)  # (M, K)
    out: list[str | None] = []
    for k in range(len(xy)):
        near = np.flatnonzero(d[:, k] <= LABEL_DISTANCE_M)
        classes = {CLASS_ALIASES.get(boxes.classes[i], boxes.classes[i]) for i in near}
        out.append(classes.pop() if len(classes) == 1 else None)
    return out


def collect(log_path: str | Path, seconds: float | None = None) -> Samples:
    """Run the node over a simulated log on its true poses (labels need the true world, and
    the attributes do not depend on where the pose came from) and label the classified
    tracks of every cycle with the true boxes of that sweep."""
    import kd_store
    from logs.source import open_log
    from wm.config import NodeConfig, PoseSource
    from wm.node import WorldModelNode

    config = NodeConfig(pose_source=PoseSource.TRUTH, odometry_process=False)
    source = open_log(Path(log_path))
    name = Path(log_path).name
    out = Samples([], [], [])
    boxes_at: dict[int, ObjectBoxes] = {}
    first_t: int | None = None
    n_boxes = 0
    with kd_store.open(":memory:", run="new", source=str(log_path)) as kd:
        node = WorldModelNode(kd, config, None)
        with node:
            for frame in source.frames():
                first_t = frame.t_ns if first_t is None else first_t
                if seconds is not None and frame.t_ns - first_t > seconds * 1e9:
                    break
                if isinstance(frame, ObjectBoxes):
                    boxes_at[frame.t_ns] = frame
                    n_boxes += 1
                for c in node.feed(frame):
                    _take(node, boxes_at, c.t_ns, name, out)
            for c in node.finish():
                _take(node, boxes_at, c.t_ns, name, out)
    if n_boxes == 0:
        raise FitError(f"{log_path}: no ground-truth objects ({ObjectBoxes.__name__}) to fit on")
    return out


def _take(node, boxes_at: dict[int, ObjectBoxes], t_ns: int, name: str, out: Samples) -> None:
    """Label this cycle's classified tracks with the truth of the sweep it ran on."""
    if node.sp is None or t_ns not in boxes_at:
        return
    boxes = boxes_at.pop(t_ns)
    for t in [t for t in boxes_at if t < t_ns]:
        del boxes_at[t]  # older sweeps' truth will not be asked for again
    objects = node.sp.level4
    ks, rows = objects.class_rows()
    tr = objects.tracker.tracks
    for k, row, label in zip(ks, rows, label_tracks(tr.x[ks, :2], boxes), strict=True):
        if label is not None:
            out.rows.append(row)
            out.labels.append(TRUE_TO_LIBRARY.get(label, label))
            out.tracks.append((name, int(tr.id[k])))


@dataclass(frozen=True)
class FittedClass:
    """One class's fitted prototype: value and weight (1 / std of ``log(x + eps)``) per
    attribute, with the samples and tracks it came from."""

    name: str
    attributes: dict[str, float]
    weights: dict[str, float]
    samples: int
    tracks: int


def fit(samples: Samples, attributes: Sequence[str] = FIT_ATTRIBUTES) -> list[FittedClass]:
    """Per class with at least ``MIN_SAMPLES`` samples: per attribute, the mean and standard
    deviation of ``log(x + eps)`` over the samples that have it (the 1st to 99th percentile,
    so a few broken segments do not set the spread)."""
    from sp.classify import attribute_matrix, log_features

    by_class: dict[str, list[int]] = defaultdict(list)
    for i, c in enumerate(samples.labels):
        by_class[c].append(i)
    out = []
    for c, idx in sorted(by_class.items()):
        if len(idx) < MIN_SAMPLES:
            log.warning("class %r: %d samples, fewer than %d; not fitted", c, len(idx), MIN_SAMPLES)
            continue
        F = log_features(attribute_matrix([samples.rows[i] for i in idx], attributes), attributes)
        values, weights = _centre_spread(F, attributes)
        tracks = len({samples.tracks[i] for i in idx})
        out.append(FittedClass(c, values, weights, len(idx), tracks))
    return out


def _centre_spread(
    F: np.ndarray, attributes: Sequence[str]
) -> tuple[dict[str, float], dict[str, float]]:
    """Per attribute (column of ``F``, log features, NaN unobserved) with ``MIN_SAMPLES``
    values: the prototype value ``exp(mean) - eps`` and weight ``1 / std`` (floored); for an
    ``AT_MOST`` attribute (speed) the value is the most the class usually showed (its
    ``USUAL_MOST`` percentile), which the classifier penalises only exceeding."""
    from sp.classify import AT_MOST, DEFAULT_EPS, EPS

    values, weights = {}, {}
    for j, a in enumerate(attributes):
        f = F[:, j][np.isfinite(F[:, j])]
        if len(f) < MIN_SAMPLES:
            continue
        lo, hi = np.percentile(f, [1, 99])
        f = f[(f >= lo) & (f <= hi)]
        # "the most the class usually shows": a static class's track slides now and then as
        # more of it comes into view (a fifth of the buildings' samples show some speed, the
        # 99th percentile 5 m/s), which must not make motion evidence for it
        centre = np.percentile(f, USUAL_MOST) if a in AT_MOST else f.mean()
        values[a] = round(float(math.exp(centre) - EPS.get(a, DEFAULT_EPS)), 4)
        weights[a] = round(1.0 / max(float(f.std()), MIN_STD), 3)
    return values, weights


def fit_discriminant(
    samples: Samples,
    attributes: Sequence[str] = FIT_ATTRIBUTES,
    classes: Sequence[str] | None = None,
    balance: float = CLASS_BALANCE,
    l2: float = L2,
    optional: Sequence[str] = OPTIONAL_ATTRIBUTES,
) -> Discriminant:
    """The level-4 :class:`~kd_store.Discriminant` of ``samples``: a softmax over ``classes``
    (default: those with ``MIN_SAMPLES``) of :func:`sp.classify.discriminant_features`,
    fitted by weighted maximum likelihood (L-BFGS, ``MAX_ITER``) with a ridge ``l2`` on all
    but the biases; each sample weighs ``count(its class) ** -balance``. It states the
    class shares that weighting gives (``prior``, :func:`training_prior`) and the mean
    samples per track of each class (``views``), for ``sp.scene_prior``.

    A sample with an attribute of ``optional`` also enters a second time without it, at the
    same weight, so that the samples lacking the attribute are all the samples. Without the
    copies, an object lacking it would be classified as the training objects that lacked it
    were, those the forward camera did not see (on the shipped training logs it saw persons
    in 28 % of their samples, vehicles in 47 %), and a sensor suite without a colour camera
    would get that class mix for every object; with them, it gets the class mix of all the
    samples."""
    from scipy.optimize import minimize

    from kd_store import Level
    from sp.classify import DEFAULT_EPS, EPS, attribute_matrix, discriminant_features, log_features

    if classes is None:
        n = defaultdict(int)
        for c in samples.labels:
            n[c] += 1
        classes = sorted(c for c, k in n.items() if k >= MIN_SAMPLES)
    index = {c: i for i, c in enumerate(classes)}
    keep = [i for i, c in enumerate(samples.labels) if c in index]
    if not keep:
        raise FitError(f"no samples of the classes {list(classes)} to fit a discriminant on")
    L = log_features(attribute_matrix([samples.rows[i] for i in keep], attributes), attributes)
    y = np.array([index[samples.labels[i]] for i in keep])
    centre = np.nanmean(L, axis=0)
    if not np.all(np.isfinite(centre)):
        raise FitError(f"attributes {list(attributes)}: one is never observed in the samples")
    count = np.bincount(y, minlength=len(classes)).astype(np.float64)
    if not np.all(count > 0):
        raise FitError(
            f"classes {[c for c, n in zip(classes, count, strict=True) if not n]} have no samples"
        )
    tracks: list[set[tuple[str, int]]] = [set() for _ in classes]
    for i, k in zip(keep, y.tolist(), strict=True):
        tracks[k].add(samples.tracks[i])
    sw = count[y] ** -balance
    # the copies without the optional attributes (see the docstring)
    cols = [list(attributes).index(a) for a in optional if a in attributes]
    has = np.isfinite(L[:, cols]).any(axis=1)  # none when cols is empty
    bare = L[has].copy()
    bare[:, cols] = np.nan
    L, y = np.vstack([L, bare]), np.concatenate([y, y[has]])
    sw /= sw.sum()  # the ridge weighs against the samples as they are, not their copies
    sw = np.concatenate([sw, sw[has]])
    Z = discriminant_features(L - centre)
    D, C = Z.shape[1], len(classes)
    rows = np.arange(len(y))
    ridge = np.ones((D, 1))
    ridge[-1] = 0.0  # the biases carry the class balance: no ridge on them

    def nll(w: np.ndarray) -> tuple[float, np.ndarray]:
        W = w.reshape(D, C)
        S = Z @ W
        S -= S.max(axis=1, keepdims=True)
        lse = np.log(np.exp(S).sum(axis=1))
        P = np.exp(S - lse[:, None])
        P[rows, y] -= 1.0
        value = -float((sw * (S[rows, y] - lse)).sum()) + l2 * float((ridge * W**2).sum())
        grad = Z.T @ (P * sw[:, None]) + 2.0 * l2 * ridge * W
        return value, grad.ravel()

    r = minimize(nll, np.zeros(D * C), jac=True, method="L-BFGS-B",
                 options={"maxiter": MAX_ITER})  # fmt: skip
    log.info("discriminant: %d samples (%d copies without %s), %d classes, %d iterations, %s",
             len(y), int(has.sum()), list(optional), C, r.nit, r.message)  # fmt: skip
    if not r.success:
        log.warning("discriminant fit did not converge (%s): the weights are the last iterate",
                    r.message)  # fmt: skip
    W = r.x.reshape(D, C)
    return Discriminant(
        Level.OBJECT,
        tuple(attributes),
        tuple(EPS.get(a, DEFAULT_EPS) for a in attributes),
        tuple(round(float(c), 6) for c in centre),
        tuple(classes),
        tuple(tuple(round(float(v), 6) for v in row) for row in W),
        training_prior(count, balance),
        tuple(round(float(count[c] / len(tracks[c])), 3) for c in range(C)),
    )


def training_prior(count: np.ndarray, balance: float) -> tuple[float, ...]:
    """The class shares (C,) a fit weighing each sample by ``count(its class) ** -balance``
    gives the classes of ``count`` (C,) samples: ``count ** (1 - balance)``, normalised."""
    share = np.asarray(count, dtype=np.float64) ** (1.0 - balance)
    return tuple(float(v) for v in share / share.sum())


def to_yaml(
    fitted: Iterable[FittedClass],
    provenance: Mapping[str, object],
    discriminant: Discriminant | None = None,
) -> str:
    """The fitted prototypes (and discriminant) as a class-library overlay
    (``kd_store/classes_fitted.yaml``)."""
    rows = [
        {
            "name": f.name,
            "fitted": {"samples": f.samples, "tracks": f.tracks},
            "attributes": {a: [f.attributes[a], f.weights[a]] for a in f.attributes},
        }
        for f in fitted
    ]
    head = (
        "# Level-4 class prototypes fitted by wm/fit_classes.py (values: exp(mean log(x + eps))"
        " - eps;\n# weights: 1 / std of log(x + eps)) and the discriminant that scores them"
        " (kd_store.Discriminant).\n# Generated; do not edit by hand.\n"
    )
    doc: dict[str, object] = {"provenance": dict(provenance), "classes": rows}
    if discriminant is not None:
        d = discriminant
        doc["discriminant"] = {
            "level": int(d.level),
            "attributes": list(d.attributes),
            "eps": list(d.eps),
            "centre": list(d.centre),
            "classes": list(d.classes),
            "weights": [list(r) for r in d.weights],
        }
        if d.prior is not None:
            doc["discriminant"]["prior"] = list(d.prior)
        if d.views is not None:
            doc["discriminant"]["views"] = list(d.views)
    return head + yaml.safe_dump(
        doc,
        sort_keys=False,
        width=100,
        default_flow_style=None,
    )


def main(argv: Sequence[str] | None = None) -> int:
    from fixtures import SIMULATOR_VERSION
    from wm.eval_sweep import EVAL_SEEDS

    ap = argparse.ArgumentParser(
        prog="python -m wm.fit_classes", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--scenarios", nargs="+", help="default: those of TRAINING_SETS")
    ap.add_argument(
        "--seeds", nargs="+", type=int,
        help="default: each scenario's TRAINING_SETS (TRAINING_SEEDS for one not in it)",
    )  # fmt: skip
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--cache", default="out/eval-logs", help="simulated logs (made when missing)")
    ap.add_argument("--jobs", type=int, default=2, help="logs collected side by side")
    ap.add_argument("--out", default="kd_store/classes_fitted.yaml")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sets = {
        s: tuple(args.seeds or TRAINING_SETS.get(s, TRAINING_SEEDS))
        for s in args.scenarios or TRAINING_SCENARIOS
    }
    bad = sorted(set().union(*sets.values()) & set(EVAL_SEEDS))
    if bad:
        raise FitError(f"seeds {bad} are evaluation seeds (docs/evaluation.md): never fit on them")
    cache = Path(args.cache)
    runs = [(sc, seed) for sc, seeds in sets.items() for seed in seeds]
    log.info("%d training logs in %s (those missing are simulated first)", len(runs), cache)
    # logs missing from the cache are simulated side by side too (a process each)
    with ThreadPoolExecutor(max(1, args.jobs)) as threads:
        paths = list(threads.map(lambda run: _log(*run, args.seconds, cache), runs))
    samples = Samples([], [], [])
    for k, (path, s) in enumerate(zip(paths, _collect_all(paths, args.jobs), strict=True)):
        log.info("[%d/%d] %s: %d labelled samples", k + 1, len(paths), path.name, len(s))
        samples.extend(s)
    fitted = fit(samples)
    discriminant = fit_discriminant(samples, classes=[f.name for f in fitted])
    provenance = {
        "seeds": {s: list(seeds) for s, seeds in sets.items()},
        "seconds": args.seconds,
        "simulator_version": SIMULATOR_VERSION,  # the logs' (fixtures.SIMULATOR_VERSION)
        "samples": len(samples),
        "attributes": list(FIT_ATTRIBUTES),
        "usual_most_percentile": USUAL_MOST,
        "class_balance": CLASS_BALANCE,
        "l2": L2,
    }
    Path(args.out).write_text(to_yaml(fitted, provenance, discriminant))
    for f in fitted:
        log.info("%-18s %6d samples %4d tracks", f.name, f.samples, f.tracks)
    return 0


def _collect_all(paths: Sequence[Path], jobs: int) -> Iterator[Samples]:
    """The samples of each log, in the order of ``paths`` whatever order they finish in.

    With ``jobs > 1`` each log is read in a process of its own (a node is single-threaded).
    The processes are spawned, not forked: a fork of a caller that has run OpenMP or other
    threads (a notebook, a test process) may die or hang in the child."""
    if jobs <= 1:
        yield from map(collect, paths)
        return
    import multiprocessing as mp

    with ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn")) as pool:
        yield from pool.map(collect, paths)


def _log(scenario: str, seed: int, seconds: float, cache: Path) -> Path:
    """The simulated training log (made when the cache lacks it)."""
    from wm.eval_sweep import simulate_cached

    return simulate_cached(scenario, seed, seconds, cache, timeout_s=1800.0)


if __name__ == "__main__":
    sys.exit(main())

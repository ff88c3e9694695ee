"""The class prior of the scene in view, learned while the run goes on.

A fitted discriminant (``kd_store.Discriminant``) gives p(c | x) under the class shares it was
fitted with (``Discriminant.prior``: the training mix, reweighted by its class balance). A
street has no rocks and many cars, an open field the reverse, and a classifier that keeps the
training mix names a far, partial car seen by a dozen returns a rock as readily on a street as
in a field. Bayes' rule exchanges the prior:

    p_s(c | x) = p(c | x) * w_c / sum_k p(k | x) * w_k,   w_c = pi_s(c) / pi_t(c),

and the scene's prior is estimated from the same posteriors by expectation maximisation
(Saerens, Latinne and Decaestecker 2002, "Adjusting the outputs of a classifier to new a priori
probabilities", Neural Computation 14(1)): the scene's class shares are the mean of the
posteriors adjusted to them, found by iterating from the last estimate.

What the scene holds is counted in objects, not in views: a car passed slowly is seen in a
hundred sweeps and a scan of three sweeps sees each object three times, but each is one car
of the scene. An object's attributes are its track's running estimates, so its latest view
stands for all of them (its views are not independent draws), and its likelihood of class c
is that view's ``p(c | x) / pi_t(c)``. Expectation maximisation over the objects gives the
scene's object shares ``rho``; the discriminant's prior is one of views, so the two are tied
by the mean views per object of each class in training (``Discriminant.views``, v_c):
``pi_s(c) ~ rho(c) v_c``. The estimate holds the latest ``window`` objects seen (the scene in
view, not the whole drive) and ``strength`` pseudo-objects of the training mix (a Dirichlet
prior): a run starts at the training mix and leaves it only as far as the objects it has seen
carry it.

Reference 001, 4.4.3 (the world model's class knowledge serves classification) and 4.5.1
(classification compares attributes with the prototypes of classes): what the world model has
seen of this place so far is knowledge a class decision may use.

A view is one measurement of a confirmed object in one sweep, as the discriminant's training
samples are (``wm.fit_classes``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from core.errors import EngineError


class ScenePriorError(EngineError, ValueError):
    """A prior or a batch of posteriors the scene prior cannot use; names the value."""


class ScenePrior:
    """Estimate of the scene's class shares over ``classes``.

    train_prior: (C,) the view shares the classifier's probabilities carry (positive, sum 1).
    views:       (C,) the mean views per object of each class in training (>= 1).
    strength:    pseudo-objects of the training mix in the estimate (> 0).
    window:      the estimate rests on the latest this many objects seen (>= 1).
    """

    def __init__(
        self,
        classes: Sequence[str],
        train_prior: Sequence[float],
        views: Sequence[float],
        strength: float,
        window: int = 300,
    ) -> None:
        C = len(classes)
        pi_t = np.asarray(train_prior, dtype=np.float64)
        v = np.asarray(views, dtype=np.float64)
        if pi_t.shape != (C,) or not np.all(pi_t > 0) or abs(pi_t.sum() - 1) > 1e-3:
            raise ScenePriorError(
                f"training prior {pi_t.tolist()} is not {C} positive shares summing to 1"
            )
        if v.shape != (C,) or not np.all(v >= 1):
            raise ScenePriorError(f"views per object {v.tolist()} are not {C} counts >= 1")
        if not strength > 0:
            raise ScenePriorError(f"scene prior strength {strength} is not > 0")
        if window < 1:
            raise ScenePriorError(f"scene prior window {window} is not >= 1")
        self.classes = tuple(classes)
        self.pi_t = pi_t / pi_t.sum()
        self.v = v
        self.strength = float(strength)
        self.window = int(window)
        # the training mix in objects: view shares over views per object
        self.rho_t = _unit(self.pi_t / v)
        self.rho = self.rho_t.copy()  # (C,) the scene's object shares as estimated (sum 1)
        # each held object's likelihoods (its latest view's posterior over pi_t) in a slot of
        # (window, C) rows, and when it was last seen (count of observe calls)
        self._slot: dict[int, int] = {}
        self._id_of = np.zeros(self.window, dtype=np.int64)
        self._L = np.zeros((self.window, C))
        self._seen = np.zeros(self.window, dtype=np.int64)
        self._calls = 0

    @property
    def pi_s(self) -> np.ndarray:
        """(C,) the scene's view shares as estimated (sum 1)."""
        return _unit(self.rho * self.v)

    @property
    def weights(self) -> np.ndarray:
        """(C,) ``w_c = pi_s(c) / pi_t(c)``, the factors that exchange the priors."""
        return self.pi_s / self.pi_t

    @property
    def n_objects(self) -> int:
        """Objects the estimate rests on."""
        return len(self._slot)

    def observe(
        self, ids: Sequence[int], P: np.ndarray, iterations: int = 20, tol: float = 1e-4
    ) -> None:
        """Add views and update the estimate: ``ids`` (R,) the objects seen, P (R, C) their
        views' posteriors under the training prior (rows sum to 1, or are all zero for a view
        no class is plausible for, which is not kept). Expectation maximisation from the last
        estimate, at most ``iterations`` steps, until no share moves by ``tol``."""
        P = np.asarray(P, dtype=np.float64)
        if P.ndim != 2 or P.shape != (len(ids), len(self.classes)):
            raise ScenePriorError(
                f"posteriors of shape {P.shape} for {len(ids)} views of {len(self.classes)} classes"
            )
        s = P.sum(axis=1)
        if not np.all(np.isfinite(P)) or np.any(np.abs(s[s > 0] - 1.0) > 1e-6):
            raise ScenePriorError("posteriors must be finite rows summing to 1 (or 0)")
        self._calls += 1
        keep = s > 0
        # each object's likelihood of each class (to a factor per object)
        for i, row in zip(np.asarray(ids)[keep].tolist(), P[keep] / self.pi_t, strict=True):
            k = self._slot.get(i)
            if k is None and len(self._slot) < self.window:  # a free slot
                k = len(self._slot)
                self._slot[i] = k
                self._id_of[k] = i
            elif k is None:  # the slot of the object seen longest ago
                k = int(self._seen.argmin())
                del self._slot[int(self._id_of[k])]
                self._slot[i] = k
                self._id_of[k] = i
            self._L[k] = row
            self._seen[k] = self._calls
        if not self._slot:
            return
        L = self._L[: len(self._slot)]
        Q = np.empty_like(L)
        for _ in range(iterations):
            # E: each object's posterior under the present object shares (every held row has
            # a plausible class); M: their mean, with the training mix's pseudo-objects
            np.multiply(L, self.rho, out=Q)
            Q /= Q.sum(axis=1, keepdims=True)
            rho = (Q.sum(axis=0) + self.strength * self.rho_t) / (len(L) + self.strength)
            moved = float(np.abs(rho - self.rho).max())
            self.rho = rho
            if moved < tol:
                break


def _unit(x: np.ndarray) -> np.ndarray:
    return x / x.sum()


def adjust(P: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Posteriors P (R, C) under one prior moved to the prior ``w`` times it (w (C,) > 0):
    each row times ``w``, renormalised; an all-zero row stays zero."""
    Q = P * w
    s = Q.sum(axis=1, keepdims=True)
    return np.where(s > 0, Q / np.where(s > 0, s, 1.0), 0.0)

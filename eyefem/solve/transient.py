"""Gradients through time: the adjoint of a load path whose terms carry a history from
step to step (a cavity's volume regulation, eyefem.fem.regulation).

Step k solves R(q_k, theta_k) = 0, where theta_k holds the history h_{k-1} the step
started from (params ``term.history_keys``), and ends with h_k = H(q_k, theta_k)
(``term.history_after``). An output J(q_N, theta_N) of the last step depends on the
design through every step. Backwards from the last step, one adjoint per step
(eyefem.solve.adjoint.value_and_grad at that step's state, on a fresh factorisation):

    step N:     g_N = dJ/dtheta_N;                         lambda = g_N[history]
    step k < N: g_k = d(lambda . H(q_k, theta_k))/dtheta_k; lambda = g_k[history]

g_k is the derivative of J with respect to step k's own theta (history chained through
the later steps): a param held at one value over the steps has the derivative sum_k
g_k[param]; one ramped by a stage, sum_k w_k g_k[param] with w_k its weight in theta_k
(:func:`ramp_weights`). Prescribed dofs and contact pairs are those of each step. The
chain stops where no active term carries a history back and at the first step of a
stage with a ``before`` hook (closing a cavity sets its history: derivatives through the
hook's state, such as the closing volume, are not followed). The cost is one
factorisation and one adjoint solve per step.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import jax.numpy as jnp
import numpy as np

from eyefem.solve.adjoint import value_and_grad, values_and_grads
from eyefem.solve.assembly import Assembler
from eyefem.solve.loadpath import Stage
from eyefem.solve.records import Solution


@dataclasses.dataclass
class Recorder:
    """An ``on_step`` callback of :func:`eyefem.solve.loadpath.solve` that keeps every
    step's stage, model, state and theta (the step's own: its ``dt`` and the history it
    started from), for :func:`history_gradients`, and its StepRecord (``records``: its
    iterations, balance). ``then``: a further on_step to call."""

    stages: Sequence[Stage]
    beta: float = 1.0
    then: Callable | None = None
    steps: list = dataclasses.field(default_factory=list)
    records: list = dataclasses.field(default_factory=list)

    def __call__(self, rec, model, q, theta):
        self.steps.append((rec.stage, rec.t, model, np.array(q), theta))
        self.records.append(rec)
        if self.then is not None:
            self.then(rec, model, q, theta)

    def stage(self, name: str) -> Stage:
        return next(s for s in self.stages if s.name == name)


def _history_terms(model, active):
    return [t for t in model.terms if getattr(t, "history_keys", ())
            and (active is None or t.name in active)]


def _carried(terms) -> Callable:
    """(q, theta, lam) -> [sum over terms and history keys of lam . H(q, theta)] (1,)."""
    def carried(q, theta, lam):
        out = jnp.zeros(())
        for t in terms:
            h = t.history_after(q, theta[t.name])
            for key, w in lam[t.name].items():
                out = out + jnp.sum(w * h[key])
        return jnp.reshape(out, (1,))
    return carried


def history_gradients(objective: Callable[[Any, Any], Any], recorder: Recorder,
                      first: int = 0) -> tuple[float, list]:
    """Value of objective(q, theta) at the last recorded step and its derivatives with
    respect to the theta of every step from ``first`` on (module docstring).

    Returns (value, [g_k]), g_k a pytree like step k's theta (zero where nothing later
    depends on it)."""
    steps = recorder.steps[first:]
    grads: list = [None] * len(steps)
    lam: dict = {}
    asms: dict = {}
    carried: dict = {}
    value = None
    for k in range(len(steps) - 1, -1, -1):
        name, _, model, q, theta = steps[k]
        stage = recorder.stage(name)
        if (name, id(model)) not in asms:
            mask = np.zeros(model.n_dof, bool)
            mask[stage.prescribed[0]] = True
            asms[(name, id(model))] = Assembler(model, mask, beta=recorder.beta)
        sol = Solution(model, q, theta, [], asms[(name, id(model))], None, stage.active)
        if k == len(steps) - 1:
            value, g = value_and_grad(objective, sol)
        else:
            terms = tuple(_history_terms(model, stage.active))
            if tuple(map(id, terms)) not in carried:  # compiled once per set of terms
                carried[tuple(map(id, terms))] = _carried(terms)
            lam_k = {t.name: {key: jnp.asarray(lam.get(t.name, {}).get(key, 0.0))
                              for key in t.history_keys} for t in terms}
            _, (g,) = values_and_grads(carried[tuple(map(id, terms))], sol, data=lam_k)
        grads[k] = g
        lam = {t.name: {key: np.asarray(g[t.name][key]) for key in t.history_keys}
               for t in _history_terms(model, stage.active)}
        starts_stage = k == 0 or steps[k - 1][0] != name
        if not lam or (starts_stage and stage.before is not None):
            break  # nothing carried back, or a hook (closing a cavity) set the history
    return value, grads


def ramp_weights(recorder: Recorder, stage: str, first: int = 0) -> np.ndarray:
    """The weight of a stage's param target in each recorded step's theta (from
    ``first`` on): the step's load factor t within that stage, 1 in the later stages
    (where the target is held), 0 before; a param a later stage ramps again is not
    covered."""
    names = [s.name for s in recorder.stages]
    i = names.index(stage)
    w = []
    for name, t, *_ in recorder.steps[first:]:
        j = names.index(name)
        w.append(0.0 if j < i else t if j == i else 1.0)
    return np.array(w)


def total(grads: list, term: str, key: str, weights=None) -> Any:
    """sum_k w_k g_k[term][key] (weights default 1: a param held over the steps)."""
    w = np.ones(len(grads)) if weights is None else np.asarray(weights)
    return sum(wk * np.asarray(g[term][key]) for wk, g in zip(w, grads)
               if g is not None and wk != 0.0)


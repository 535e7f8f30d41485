"""A staged procedure as data, and the gradient of its outcomes by one backward sweep.

A staged procedure (a surgery: pressurise, tighten, suture) is a chain of equilibria
R_k(q_k, theta_k) = 0, k = 1..N, whose params are functions of the design and of what
the earlier stages hand on:

    theta_k = T_k(design, c_{<k}),      c_k = C_k(q_k, theta_k),      J = J(q_N, theta_N, c_{<N})

(c_{<k}: the carries of the stages before k, e.g. the cavity volume at closure, the snug
fit of a buckle, the tied suture lengths, the pre-operative optics). Each stage is a
:class:`StageMap` (its T_k and C_k, written once in JAX); the forward run evaluates them
(:func:`stage_params`, :func:`hand_on`) and :func:`staged_gradients` differentiates the
same functions. The backward sweep, for k objectives at once:

    stage N:  g_N = dJ/dtheta_N (adjoint on stage N, c held),   cbar = dJ/dc (jax.vjp)
    stage k:  g_k = d/dtheta_k [cbar_k . C_k(q_k, theta_k)]     (adjoint on stage k)
    each k:   (dbar, cbar_{<k}) += vjp of T_k at g_k restricted to T_k's params

one block adjoint solve per stage on its tangent at the converged state (the solution's
own factorisation, or a new one: eyefem.solve.records.Solution.factorised;
eyefem.solve.adjoint.values_and_grads) and a ``jax.vjp`` through each T_k and C_k.
The params a stage does not take from T_k are constants of the procedure.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.solve.adjoint import kept, values_and_grads
from eyefem.solve.records import Solution


@dataclasses.dataclass(frozen=True)
class StageMap:
    """One stage of a staged procedure: what it takes from the design and hands on.

    Attributes:
      name: the stage's name.
      params: T(design, carry, data) -> {term: {param: array}}: the params the stage takes
        from the design (name -> 0-d array) and from the carries of the earlier stages
        (name -> array); a JAX function, its arrays shaped as the stage's params.
      carry: C(q, theta, data) -> {name: array}: what the converged stage (q (n_dof,),
        theta) hands on to the later stages and the outcomes; a JAX function of its
        arguments alone (its derivatives are compiled once per function object); None:
        nothing.
    """

    name: str
    params: Callable
    carry: Callable | None = None


@dataclasses.dataclass(frozen=True)
class StageRecord:
    """A converged stage of a run: its map, its solution (with the last factorisation),
    the data of its T and C, and the carry it handed on (name -> array).

    ``names``: the record's name of each of C's carries (C's name -> the record's), where
    several records share one map: the steps of a timeline (eyefem.eye.timeline) hand on
    "iop" and "history" each, kept apart as "iop/7", "history/7" (C is compiled once for
    all of them); ``carry`` holds the record's names. Default: C's own names."""

    map: StageMap
    solution: Solution
    params_data: Any = None
    carry_data: Any = None
    carry: Mapping = dataclasses.field(default_factory=dict)
    names: Mapping = dataclasses.field(default_factory=dict)


def _as_jax(tree):
    return jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), tree)


def stage_params(stage: StageMap, design: Mapping, carry: Mapping, data=None) -> dict:
    """T_k evaluated (numpy leaves): the params the stage takes from ``design`` (name ->
    float) and the earlier stages' ``carry``."""
    out = stage.params(_as_jax(dict(design)), _as_jax(dict(carry)), data)
    return jax.tree_util.tree_map(np.asarray, out)


def params_mismatch(records: Sequence["StageRecord"], design: Mapping,
                    checked: Callable[[Any], bool] = lambda record: True) -> float:
    """The largest difference, relative to the param's size, between the params each
    ``checked`` stage's map gives (:func:`stage_params` of the design and the carries
    handed on before it) and those its solution was solved with: roundoff where the
    forward run and the stage maps agree."""
    worst, carry = 0.0, {}
    for r in records:
        if checked(r):
            for term, ps in stage_params(r.map, design, carry, r.params_data).items():
                for k, v in ps.items():
                    ref = np.asarray(r.solution.theta[term][k])
                    scale = max(float(np.max(np.abs(ref), initial=0.0)), 1e-12)
                    worst = max(worst, float(np.max(np.abs(np.asarray(v) - ref),
                                                    initial=0.0)) / scale)
        carry.update(r.carry)
    return worst


def hand_on(stage: StageMap, q, theta, data=None) -> dict:
    """C_k evaluated at a converged state (name -> numpy arrays, or a dict of them); {}
    without a carry."""
    if stage.carry is None:
        return {}
    out = compiled(stage.carry)(jnp.asarray(q), _as_jax(theta), data)
    return jax.tree_util.tree_map(np.asarray, dict(out))


def compiled(fn: Callable) -> Callable:
    """``fn`` compiled (jax.jit), one per function object
    (:func:`eyefem.solve.adjoint.kept`): a stage's carry or an outcome function evaluated
    at a converged state runs one XLA program, where eager JAX compiles and keeps one per
    operation."""
    return kept(fn, "compiled", jax.jit)


def contracted(carry_fn: Callable) -> Callable:
    """(q, theta, data) -> (k,): cbar . C(q, theta) for data = {"cbar": like C's carry,
    each array with a leading k, "data": C's data}, the objective of a stage's adjoint;
    one object per C."""
    def build(C):
        def objective(q, theta, data):
            full = C(q, theta, data["data"])
            c = {name: full[name] for name in data["cbar"]}
            terms = jax.tree_util.tree_map(
                lambda b, v: jnp.reshape(b, (b.shape[0], -1)) @ jnp.ravel(v), data["cbar"], c)
            return sum(jax.tree_util.tree_leaves(terms))
        return objective
    return kept(carry_fn, "contracted", build)


def holding_carry(objectives: Callable) -> Callable:
    """(q, theta, data) -> (k,): objectives(q, theta, carry, data) with data = {"carry":
    ..., "data": ...}: the last stage's objective with the carries held; one object per
    objective function."""
    def build(J):
        def objective(q, theta, data):
            return J(q, theta, data["carry"], data["data"])
        return objective
    return kept(objectives, "holding_carry", build)


def _carry_pullback(objectives: Callable) -> Callable:
    """(q, theta, carry, data) -> dJ/dcarry with a leading k (compiled once per objective
    function): the objectives' direct dependence on the carries."""
    def build(J):
        def pull(q, theta, carry, data):
            vals, vjp = jax.vjp(lambda c: J(q, theta, c, data), carry)
            return jax.vmap(vjp)(jnp.eye(vals.shape[0], dtype=vals.dtype))[0]
        return jax.jit(pull)
    return kept(objectives, "carry_pullback", build)


def staged_gradients(records: Sequence[StageRecord], design: Mapping, objectives: Callable,
                     data=None) -> tuple[np.ndarray, list[dict[str, float]]]:
    """Values and design gradients of k objectives of a staged run (module docstring).

    Args:
      records: the run's converged stages, in order (:class:`StageRecord`).
      design: name -> float, the design the run was made at.
      objectives: J(q, theta, carry, data) -> (k,), a JAX function of its arguments alone
        (pass the same object at every design: its derivatives are compiled once), at the
        last stage's state; carry: every stage's carry but the last's.
      data: J's data (a pytree of arrays).
    Returns: (values (k,), k dicts design name -> dJ_j / d design).
    """
    design_j = {k: jnp.asarray(float(v), jnp.float64) for k, v in design.items()}
    before = [dict() for _ in records]  # the carries before each stage
    acc: dict = {}
    for i, rec in enumerate(records):
        before[i] = dict(acc)
        acc.update(rec.carry)
    last = records[-1]
    carry_last = _as_jax(before[-1])
    vals, g_last = values_and_grads(holding_carry(objectives), last.solution,
                                    data={"carry": carry_last, "data": data})
    k = len(vals)
    sol = last.solution
    cbar = jax.tree_util.tree_map(np.asarray, dict(_carry_pullback(objectives)(
        jnp.asarray(sol.q), _as_jax(sol.theta), carry_last, data)))
    totals = [dict.fromkeys(design, 0.0) for _ in range(k)]
    for i in range(len(records) - 1, -1, -1):
        rec = records[i]
        carry_in = _as_jax(before[i])
        shape, vjp = jax.vjp(lambda d, c, rec=rec: rec.map.params(d, c, rec.params_data),
                             design_j, carry_in)
        if not jax.tree_util.tree_leaves(shape):  # the stage takes nothing from the design
            continue
        if i == len(records) - 1:
            gs = g_last
        else:
            own = {v: k for k, v in rec.names.items()}  # the record's name -> C's
            mine = {own.get(n, n): cbar.pop(n) for n in rec.carry if n in cbar}
            if not mine:
                gs = None
            else:
                _, gs = values_and_grads(contracted(rec.map.carry), rec.solution,
                                         data={"cbar": _as_jax(mine),
                                               "data": rec.carry_data})
        if gs is None:
            continue
        for j, g in enumerate(gs):
            ct = {t: {p: jnp.asarray(g[t][p], jnp.float64).reshape(np.shape(v))
                      for p, v in params.items()} for t, params in shape.items()}
            gd, gc = vjp(ct)
            for name, v in gd.items():
                totals[j][name] += float(v)
            for name, v in gc.items():
                if not any(np.any(np.asarray(a)) for a in jax.tree_util.tree_leaves(v)):
                    continue  # T reads no such carry (a timeline's step reads one of many)
                if name not in cbar:
                    cbar[name] = jax.tree_util.tree_map(
                        lambda a: np.zeros((k,) + np.shape(a)), v)
                cbar[name] = jax.tree_util.tree_map(
                    lambda acc, a, j=j: acc + np.eye(k)[j].reshape((k,) + (1,) * np.ndim(a))
                    * np.asarray(a), cbar[name], v)
    return np.asarray(vals), totals

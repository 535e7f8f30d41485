"""Adjoint gradients of a surgery's outcomes with respect to its design variables.

:class:`DesignGradients` is the gradient half of eyefem.eye.design.SurgerySimulator: three
adjoint solves per outcome (stages 3, 2 and the pre-operative stage 1), each reusing the
last Newton factorisation of its stage, chained through the maps from the design to the
stages' params (eyefem.eye.design's module docstring has the equations).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.eye.outcomes import changes, eye_optics
from eyefem.eye.parts import snug_scale
from eyefem.eye.rigid_buckle import suture_frame, suture_layout
from eyefem.eye.sutures import radial_bite_sensitivity
from eyefem.eye.variables import (
    DESIGN_VARIABLES,
    OPTICAL_CHANGES,
    OUTCOMES,
    STAGE_PARAMS,
)
from eyefem.fem.cavity import cavity_pressures
from eyefem.solve.adjoint import values_and_grads


def term_kind(term) -> tuple:
    """The key of the compiled functions of a term's state, one per kind whatever the
    design: its class and static configuration, as the model's kernels are keyed
    (eyefem.solve.model.Model._kernel: its methods read arrays only from their arguments)."""
    return (type(term), term.static_key())


class DesignGradients:
    """d outcome / d design variable of a converged design (mixed into SurgerySimulator,
    whose attributes it reads: parts, params, model, preop, pulled, the outcome nodes and
    the cache of compiled outcome functions). The objectives of the three stages are
    functions of (state, params, data) kept one per outcome list and kind, so that their
    derivatives are compiled once (eyefem.solve.adjoint.values_and_grads)."""

    def _kept_fn(self, key, build: Callable) -> Callable:
        """The function cached under ``key`` (built by ``build()`` the first time)."""
        if key not in self._compiled:
            self._compiled[key] = build()
        return self._compiled[key]

    def _preop_routes(self, res, names, weights=None) -> tuple[Callable, dict] | None:
        """(f, data): f(q1, data) -> (k,) the named outcomes with the state held at ``res``
        and the pre-operative eye at q1 ((1,) their weighted sum with ``weights``); their
        gradients are the outcomes' dependence on the pre-operative state (0 for the
        outcomes that do not depend on it). None if none does."""
        if not set(names) & set(OPTICAL_CHANGES):
            return None
        names = tuple(names)
        X, nodes = self.parts.eye.mesh.nodes, self._nodes

        def build():
            def routes(q1, data):
                ch = changes(data["now"], eye_optics(X, q1, nodes))
                v = jnp.stack([ch[n] if n in OPTICAL_CHANGES else jnp.zeros(()) for n in names])
                w = data["weights"]
                return v if w is None else jnp.reshape(jnp.dot(w, v), (1,))
            return routes

        fn = self._kept_fn(("routes", names, weights is None), build)
        now = {k: jnp.asarray(float(v)) for k, v in eye_optics(X, res.sol3.q, nodes).items()}
        return fn, {"now": now, "weights": None if weights is None else jnp.asarray(weights)}

    # --- adjoint ------------------------------------------------------------------
    def gradients(self, res, outcomes=None) -> dict[str, dict[str, float]]:
        """d outcome / d design variable for the named outcomes (default: all OUTCOMES):
        three block adjoint solves (stages 3, 2, 1), one right-hand side per outcome."""
        names = list(OUTCOMES) if outcomes is None else list(outcomes)
        totals = self._gradients(res, self.outcome_vector(res, names),
                                 self._preop_routes(res, names))
        return dict(zip(names, totals))

    def weighted_gradient(self, res, weights: dict) -> dict[str, float]:
        """d (sum_k w_k outcome_k) / d design variable, for outcome name -> weight w_k: the
        cost of one outcome's gradient (three adjoint solves) whatever the weights (the
        backward pass of eyefem.simulate)."""
        items = [(k, float(w)) for k, w in weights.items() if w]
        if not items:
            return {k: 0.0 for k in DESIGN_VARIABLES}
        names = [k for k, _ in items]
        w = np.array([w for _, w in items])
        return self._gradients(res, self.outcome_vector(res, names, w),
                               self._preop_routes(res, names, w))[0]

    def _gradients(self, res, objectives, routes) -> list[dict[str, float]]:
        """d objective / d design for k objectives, ``objectives`` = (f, data) with
        f(q, theta, data) (k,), and their stage-1 routes (f(q1, data) (k,), data) or None:
        the adjoints of stages 3, 2 and 1, each stage's k adjoints solved together
        (eyefem.solve.adjoint.values_and_grads), chained through the design map
        (SurgerySimulator.design_map, by jax.vjp) and the bites' derivatives."""
        sut, pre = res.sutures, res.preop or self.preop
        rs = self.parts.eye.geometry.scleral_radius
        fn, data = objectives
        _, g3s = values_and_grads(fn, res.sol3, data=data)
        gL0 = jnp.stack([jnp.asarray(g3["sutures"]["L0"]) for g3 in g3s])  # (k, n_bars)

        def build():
            def tied_lengths(q, theta, data):
                weights, sut_data, sut_dofs = data
                return weights @ sut.lengths(q[sut_dofs], theta["sutures"], sut_data)
            return tied_lengths

        tied = self._kept_fn(("tied", term_kind(sut)), build)
        _, g2s = values_and_grads(tied, res.sol2, data=(gL0, sut.data, sut.dofs))
        g_volume = [sum(float(np.sum(g["cavity"]["v_ini"])) for g in gg) for gg in zip(g2s, g3s)]
        g_scale = [rs * sum(float(np.sum(g[t]["dr"])) for g in gg for t in ("buckle", "sutures"))
                   for gg in zip(g2s, g3s)]
        g1s = self._preop_adjoints(pre, jnp.asarray(g_volume), jnp.asarray(g_scale), routes)
        dxi_w = self._dxi(res, "suture_width")
        encircling = self.parts.buckle.encircling
        dxi_m = 0 * dxi_w if encircling else self._dxi(res, "buckle_meridian_deg")
        bites = (res.sol3.theta["sutures"]["xi"], dxi_w, dxi_m, res.design["suture_width"],
                 res.design["buckle_meridian_deg"])
        design = {k: jnp.asarray(v, jnp.float64) for k, v in res.design.items()}
        totals = [dict.fromkeys(DESIGN_VARIABLES, 0.0) for _ in g3s]
        for stage, gs, like in ((1, g1s, pre.sol1.theta), (2, g2s, res.sol2.theta),
                                (3, g3s, res.sol3.theta)):
            keys = [(t, k) for t, k in STAGE_PARAMS[stage] if t in gs[0] and k in gs[0][t]]

            def params(d, like=like, keys=keys):
                values = self.design_map(d, like, bites)
                return [values[t][k] for t, k in keys]

            _, vjp = jax.vjp(params, design)
            for g, total in zip(gs, totals):
                (gd,) = vjp([jnp.asarray(g[t][k], jnp.float64) for t, k in keys])
                for k, v in gd.items():
                    total[k] += float(v)
        if encircling:  # its sutures are spread evenly around: no meridian
            for total in totals:
                total["buckle_meridian_deg"] = 0.0
        return totals

    def jacobian(self, res, variables, outcomes=None) -> np.ndarray:
        """d outcome / d variable at the converged design ``res``: array (n_outcomes,
        n_variables), rows in the order of ``outcomes`` (default: all OUTCOMES), columns
        in the order of ``variables`` (names in DESIGN_VARIABLES). Built from gradients()."""
        names = list(OUTCOMES) if outcomes is None else list(outcomes)
        variables = list(variables)
        unknown = [v for v in variables if v not in DESIGN_VARIABLES]
        if unknown:
            raise ValueError(f"unknown design variables {unknown}; known: "
                             f"{sorted(DESIGN_VARIABLES)}")
        grads = self.gradients(res, names)
        jac = [[grads[o][v] for v in variables] for o in names]
        return np.array(jac, dtype=float).reshape(len(names), len(variables))

    def _preop_adjoints(self, pre, g_volume, g_scale, routes=None) -> list:
        """Stage-1 adjoints of k objectives, solved together: d/dtheta_1 of g_volume V(q1)
        + g_scale s(q1) + routes(q1) (each (k,)), the routes by which the pre-operative eye
        enters the later stages and the outcomes (``routes``: :meth:`_preop_routes`, or
        None)."""
        cav = self.model.term("cavity")
        route_fn, route_data = (None, None) if routes is None else routes
        node = pre.node

        def build():
            def preop(q, theta, data):
                V = cavity_pressures(q, theta["cavity"], *data["cavity"])[1][0]
                out = data["g_volume"] * V + data["g_scale"] * snug_scale(self.parts, q, node)
                return out if route_fn is None else out + route_fn(q, data["routes"])
            return preop

        fn = self._kept_fn(("preop", node, route_fn), build)
        data = {"cavity": (cav.data, cav.dofs), "g_volume": g_volume, "g_scale": g_scale,
                "routes": route_data}
        return values_and_grads(fn, pre.sol1, data=data)[1]

    def _dxi(self, res, var: str):
        """d xi / d var (n_bars, 2) of the bites (var: suture_width or buckle_meridian_deg,
        per degree), exact within each bite's face (eyefem.eye.sutures.
        radial_bite_sensitivity): a bite is the radial projection of the point
        p = c + s w/2 a' beside the buckle's centre line (s = -1, +1), so
        dp/dw = s a'/2 and, the segmental buckle turning about the eye's axis z,
        dp/dmeridian = z x p (pi / 180 per degree)."""
        w, m = res.design["suture_width"], res.design["buckle_meridian_deg"]
        layout = suture_layout(self.parts, w, m)
        cen, acr, nrm = suture_frame(self.parts, m)
        ang = np.radians(self.params["suture_angle_deg"])
        a_rot = np.cos(ang) * acr + np.sin(ang) * np.cross(nrm, acr)
        out = []
        for bites, sgn in ((layout.bite_a, -1.0), (layout.bite_b, 1.0)):
            p = cen + sgn * 0.5 * w * a_rot
            dp = (sgn * 0.5 * a_rot if var == "suture_width"
                  else np.pi / 180 * np.cross([0.0, 0.0, 1.0], p))
            out.append(radial_bite_sensitivity(self.parts.eye.mesh.nodes, bites, p, dp))
        return np.concatenate(out)

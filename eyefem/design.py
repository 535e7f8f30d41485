"""Surgical design variables: warm-started simulation and adjoint gradients of outcomes.

The design of a surgery case is a dict of continuous variables (DESIGN_VARIABLES):
band tightening (mm of circumference), posterior buckle shift (mm), suture width (mm),
suture tightening (mm), drained volume (mm^3). The pre-operative stage (pressurise)
does not depend on them and is solved once. Each later stage is an equilibrium
R_k(q_k, theta_k) = 0 whose params theta_k are functions of the design, except the
tied suture length, which is the suture length at the end of stage 2:

    theta_2 = T_2(design),     theta_3 = T_3(design, L0),     L0 = lengths(q_2, theta_2)

The gradient of an outcome J(q_3, theta_3) is assembled by two adjoint solves, each
reusing the last Newton factorisation of its stage (eyefem.adjoint):

    g_3 = dJ/dtheta_3 (adjoint on stage 3, L0 held),
    g_2 = d/dtheta_2 [ g_3,L0 . lengths(q_2(theta_2), theta_2) ] (adjoint on stage 2),

then chained through the (linear, or for the suture width geometric) maps T_2, T_3.
So the history of the load path (sutures tied on the tightened eye) is differentiated,
not frozen. The contact state (which nodes touch) is smooth (buckle_contact), so the
response is smooth in the design except where a suture bite crosses a face boundary of
the sclera (the bite stays continuous; its derivative jumps) - see docs/adjoint.md.

Warm start: a new design is solved from the previous design's converged stage-2 and
stage-3 states, by continuation of the params in one step (cut automatically if
needed); the equilibria do not depend on the path (hyperelastic, frictionless).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import jax.numpy as jnp
import numpy as np

from .adjoint import value_and_grad
from .cavity import _state_kernel
from .problems.surgery import SURGERY_FIELDS, surgery, suture_layout, suture_term
from .solver import ConvergenceError, NewtonOptions, Solution, Stage, solve
from .units import MMHG

log = logging.getLogger(__name__)

DESIGN_VARIABLES = {
    "tightening": "band circumference shortening (segmental: radial push x 2 pi), mm",
    "buckle_shift": "posterior shift of the fitted buckle along the meridian, mm",
    "suture_width": "bite span across the buckle, mm",
    "suture_tightening": "shortening of each suture loop when tied, mm",
    "drain_volume": "fluid drained during stage 2, mm^3",
    "band_tension": "tension of a pulled encircling band (cases with band_tension > 0), N",
}
OUTCOMES = {
    "iop_mmhg": "post-operative IOP (cavity pressure), mmHg",
    "indentation_mm": "buckle indentation height, mm",
    "axial_length_change_mm": "axial length change since the pre-operative state, mm",
    "max_suture_force_N": "force in the most loaded suture bar, N",
}


def default_parameters(**overrides) -> dict:
    """Surgery case parameters with defaults (see eyefem.problems.surgery)."""
    p = {f.name: f.default for f in SURGERY_FIELDS}
    unknown = set(overrides) - set(p)
    if unknown:
        raise ValueError(f"unknown surgery parameters {sorted(unknown)}; known: {sorted(p)}")
    p.update(overrides)
    return p


@dataclasses.dataclass
class Result:
    """A converged design: outcome values and the two solutions the adjoint needs."""

    design: dict
    outcomes: dict
    sol2: Solution
    sol3: Solution
    sutures: object  # the suture term of this design
    newton_iterations: int


class SurgerySimulator:
    """Simulate one surgery case for many designs, with warm starts and adjoints.

    Args:
      params: surgery case parameters (eyefem.problems.surgery.SURGERY_FIELDS); the
        design variables in it are the starting design.
      materials: material overrides (name -> MooneyRivlin), as in a case file.
      options: Newton options.
    """

    def __init__(self, params: dict, materials=None, options: NewtonOptions = NewtonOptions()):
        self.params = dict(params)
        self.options = options
        setup = surgery(self.params, materials)
        self.setup, self.parts = setup, setup.parts
        s1, self.stage2, self.stage3 = setup.stages
        sol1 = solve(setup.model, [s1], options=options)
        self.stage1_iterations = sum(r.iterations for r in sol1.history)
        self.model, _, self.theta2_start = self.stage2.before(setup.model, sol1.q, sol1.theta)
        self.q1 = sol1.q
        mesh = self.parts.eye.mesh
        x1 = mesh.nodes + sol1.q[: 3 * mesh.n_nodes].reshape(-1, 3)
        self._apex, self._pole = mesh.node_set("eye/apex")[0], mesh.node_set("eye/pole")[0]
        self.axial_preop = float(np.linalg.norm(x1[self._apex] - x1[self._pole]))
        self.last: Result | None = None
        self.pulled = any(t.name == "band_pull" for t in self.model.terms)
        self._stage2_params = ("buckle", "cavity") + (("band_pull",) if self.pulled else ())

    # --- design -> params ---------------------------------------------------------
    def design0(self) -> dict:
        return {k: float(self.params[k]) for k in DESIGN_VARIABLES}

    def _theta2(self, design, sut, base):
        motion = {"d": np.full(1, design["tightening"] * self.parts.d_per_mm),
                  "s": np.full(1, design["buckle_shift"])}
        th = dict(base)
        th["buckle"] = {**base["buckle"], **motion, "ridge": self.stage2.params["buckle"]["ridge"]}
        th["sutures"] = {**sut.params, **motion}
        th["cavity"] = {**base["cavity"], "dv": -design["drain_volume"]}
        if self.pulled:
            th["band_pull"] = {"f": design["band_tension"]}
        return th

    def _tied(self, sut, q2, theta2, design):
        L = np.asarray(sut.lengths(np.asarray(q2)[sut.dofs], theta2["sutures"], sut.data))
        th = dict(theta2)
        th["sutures"] = {**theta2["sutures"], "L0": L,
                         "tightening": np.full(len(L), design["suture_tightening"] / 2)}
        return th

    def _model(self, sut):
        return self.model.with_terms([sut if t.name == "sutures" else t for t in self.model.terms])

    # --- forward ------------------------------------------------------------------
    def run(self, design: dict | None = None, *, warm: bool = True) -> Result:
        """Solve stages 2 and 3 for a design (missing variables: the case's values).

        Warm started from the previous design's converged states when there is one; if
        that continuation fails, the design is solved again along the full load path."""
        if warm and self.last is not None:
            try:
                return self._run(design, warm=True)
            except ConvergenceError as exc:
                log.warning("warm start failed (%s); solving the design from the "
                            "pre-operative state", str(exc).splitlines()[0])
        return self._run(design, warm=False)

    def _run(self, design, *, warm):
        design = {**self.design0(), **(design or {})}
        for k in design:
            if k not in DESIGN_VARIABLES:
                raise ValueError(f"unknown design variable '{k}'; known: {sorted(DESIGN_VARIABLES)}")
        fixed = "tightening" if self.pulled else "band_tension"
        if design[fixed] != self.params[fixed]:
            raise ValueError(
                f"design variable '{fixed}' = {design[fixed]} cannot vary in this case: "
                + ("its band is pulled by a tension (band_tension > 0); vary band_tension"
                   if self.pulled else "its band shortening is prescribed; make a case with "
                   "band_tension > 0 and tightening = 0 to vary the tension"))
        sut = suture_term(self.parts, self.parts.scale, design["suture_width"])
        model = self._model(sut)
        held = self.stage2.prescribed
        th2 = self._theta2(design, sut, self.theta2_start)
        prev = self.last if warm else None
        if prev is None:
            start = {**th2, **{k: self.theta2_start[k] for k in self._stage2_params}}
            sol2 = solve(model, [Stage("tighten", self.stage2.n_steps, held,
                                       params={k: th2[k] for k in self._stage2_params},
                                       active=self.stage2.active)],
                         q0=self.q1, theta=start, options=self.options)
        else:
            start = {**prev.sol2.theta, "sutures": th2["sutures"]}
            sol2 = solve(model, [Stage("tighten", 1, held,
                                       params={k: th2[k] for k in self._stage2_params},
                                       active=self.stage2.active)],
                         q0=prev.sol2.q, theta=start, options=self.options)
        th3 = self._tied(sut, sol2.q, sol2.theta, design)
        same_faces = prev is not None and np.array_equal(prev.sutures.nodes_a, sut.nodes_a)
        if same_faces:  # continuation of every param from the previous design's state
            sol3 = solve(model, [Stage("suture", 1, self.stage3.prescribed,
                                       params={k: th3[k] for k in self._stage2_params + ("sutures",)},
                                       active=self.stage3.active)],
                         q0=prev.sol3.q, theta=prev.sol3.theta, options=self.options)
        else:
            untied = {**th3, "sutures": {**th3["sutures"], "tightening": 0 * th3["sutures"]["tightening"]}}
            sol3 = solve(model, [Stage("suture", self.stage3.n_steps, self.stage3.prescribed,
                                       params={"sutures": th3["sutures"]},
                                       active=self.stage3.active)],
                         q0=sol2.q, theta=untied, options=self.options)
        its = sum(r.iterations for r in sol2.history + sol3.history)
        res = Result(design, {}, sol2, sol3, sut, its)
        res.outcomes = {k: float(f(sol3.q, sol3.theta)) for k, f in self.outcome_fns(res).items()}
        self.last = res
        return res

    # --- outcomes as JAX functions ---------------------------------------------------
    def outcome_fns(self, res: Result) -> dict[str, Callable]:
        """Outcome name -> J(q, theta), JAX-traceable, at the converged design ``res``."""
        from .problems.surgery import _buckle_coords

        parts, mesh = self.parts, self.parts.eye.mesh
        cav = res.sol3.model.term("cavity")
        nodes = parts.sclera_nodes
        a, ok = _buckle_coords(parts)
        w = parts.buckle.width
        under = nodes[ok & (np.abs(a) < w / 4)]
        beside = nodes[ok & (np.abs(a) > w / 2 + 1.5) & (np.abs(a) < w / 2 + 3.0)]
        X = mesh.nodes
        sut = res.sutures
        f = np.asarray(sut.forces(res.sol3.q, res.sol3.theta["sutures"]))
        i_max = int(np.argmax(f))

        def x_of(q, ids):
            return X[ids] + q[: 3 * mesh.n_nodes].reshape(-1, 3)[ids]

        def iop(q, theta):
            P, _, _, _ = _state_kernel(q, theta["cavity"], cav.data, cav.dofs)
            return P[0] / MMHG

        def indentation(q, theta):
            r = lambda ids: jnp.mean(jnp.linalg.norm(x_of(q, ids), axis=1))  # noqa: E731
            return r(beside) - r(under)

        def axial(q, theta):
            x = x_of(q, np.array([self._apex, self._pole]))
            return jnp.linalg.norm(x[0] - x[1]) - self.axial_preop

        def suture_force(q, theta):
            return sut.axial_forces(q[sut.dofs], theta["sutures"], sut.data)[i_max]

        return {"iop_mmhg": iop, "indentation_mm": indentation, "axial_length_change_mm": axial,
                "max_suture_force_N": suture_force}

    # --- adjoint ------------------------------------------------------------------
    def gradients(self, res: Result, outcomes=None) -> dict[str, dict[str, float]]:
        """d outcome / d design variable for the named outcomes (default: all OUTCOMES)."""
        fns = self.outcome_fns(res)
        names = list(OUTCOMES) if outcomes is None else list(outcomes)
        dxi = self._dxi_dwidth(res)
        sut = res.sutures
        out = {}
        for name in names:
            _, g3 = value_and_grad(fns[name], res.sol3)
            gL0 = jnp.asarray(g3["sutures"]["L0"])

            def tied_length(q, theta):
                return jnp.dot(gL0, sut.lengths(q[sut.dofs], theta["sutures"], sut.data))

            _, g2 = value_and_grad(tied_length, res.sol2)

            def total(term, key):
                return sum(np.sum(g[term][key]) for g in (g2, g3))

            out[name] = {
                "tightening": self.parts.d_per_mm * (total("buckle", "d") + total("sutures", "d")),
                "buckle_shift": total("buckle", "s") + total("sutures", "s"),
                "suture_width": float(sum(np.sum(np.asarray(g["sutures"]["xi"]) * dxi)
                                          for g in (g2, g3))),
                "suture_tightening": 0.5 * float(np.sum(g3["sutures"]["tightening"])),
                "drain_volume": -total("cavity", "dv"),
                "band_tension": total("band_pull", "f") if self.pulled else 0.0,
            }
            out[name] = {k: float(v) for k, v in out[name].items()}
        return out

    def _dxi_dwidth(self, res: Result, h: float = 1e-4):
        """d xi / d width (n_bars, 2) of the bites, by central differences of the suture
        geometry (no simulation; one-sided where a bite changes face within +-h)."""
        w = res.design["suture_width"]
        lay = [suture_layout(self.parts, w + e) for e in (-h, 0.0, h)]
        xi = [np.concatenate([x.bite_a.xi, x.bite_b.xi]) for x in lay]
        nd = [np.concatenate([x.bite_a.nodes, x.bite_b.nodes]) for x in lay]
        out = (xi[2] - xi[0]) / (2 * h)
        for i in range(len(out)):
            same_m, same_p = np.array_equal(nd[0][i], nd[1][i]), np.array_equal(nd[2][i], nd[1][i])
            if not (same_m and same_p):
                out[i] = (xi[2][i] - xi[1][i]) / h if same_p else (xi[1][i] - xi[0][i]) / h
        return out

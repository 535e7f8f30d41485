"""Surgical design variables: warm-started simulation and adjoint gradients of outcomes.

The design of a surgery case is a dict of continuous variables (DESIGN_VARIABLES): the
surgical ones (band tightening or tension, buckle shift and meridian, suture width and
tightening, drained volume) and material constants (MATERIAL_VARIABLES: c10 of every
tissue, the zonule's Young's modulus, the liquid's bulk modulus, the sutures' EA) for
sensitivity studies. Each stage is an equilibrium R_k(q_k, theta_k) = 0 whose params
theta_k are functions of the design and of what the earlier stages leave:

    theta_1 = T_1(design)                                   (pressurise; materials only)
    theta_2 = T_2(design, V(q_1), s(q_1))                   (tighten / place)
    theta_3 = T_3(design, V(q_1), s(q_1), L0),  L0 = lengths(q_2, theta_2)   (suture)

with V the cavity volume at which it is closed, s the snug radial scale of the fitted
buckle (params "dr" of the buckle and its sutures) and L0 the tied suture lengths. The
gradient of an outcome J(q_3, theta_3) - including the pre-operative axial length
that the axial length change is measured from - is assembled by three adjoint
solves, each reusing the last Newton factorisation of its stage (eyefem.solve.adjoint):

    g_3 = dJ/dtheta_3 (adjoint on stage 3, L0, V, s held),
    g_2 = d/dtheta_2 [ g_3,L0 . lengths(q_2(theta_2), theta_2) ] (adjoint on stage 2),
    g_1 = d/dtheta_1 [ G_V V(q_1) + G_s s(q_1) + G_a a(q_1) ] (adjoint on stage 1),

with G_V, G_s the totals of g_2 + g_3 over v_ini and dr, G_a = -1 for the axial length
change (a: pre-operative axial length); then chained through the (linear, or for the
suture bites geometric) maps T_k. So the history of the load path (sutures tied on
the tightened eye, buckle fitted on the inflated eye) is differentiated, not frozen.
The contact state (which nodes touch) is smooth (buckle_contact), so the response is
smooth in the design except where a suture bite crosses a face boundary of the sclera
(the bite stays continuous; its derivative jumps) or the snug buckle's touching node
changes - see docs/adjoint.md.

The buckle and sutures are fitted once, on the case's own pre-operative eye and at its
meridian; a design moves them by params (shift, radial fit "dr", turn "rot" about the
eye axis), so every outcome is measured at the case's buckle position (the retinal
break): a moved buckle indents less there.

Warm start: a new design is solved from the previous design's converged states, by
continuation of the params in one step (cut automatically if needed); the equilibria
do not depend on the path (hyperelastic, frictionless). Stage 1 is solved again only
when a material constant changes.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import jax.numpy as jnp
import numpy as np

from eyefem.eye.surgery import (
    SEED_MATERIALS,
    SURGERY_FIELDS,
    snug_node,
    snug_scale,
    surgery,
    suture_layout,
    suture_term,
)
from eyefem.fem.cavity import cavity_pressures, cavity_state, close_cavity
from eyefem.fem.units import MMHG
from eyefem.solve.adjoint import value_and_grad
from eyefem.solve.solver import ConvergenceError, NewtonOptions, Solution, Stage, solve

log = logging.getLogger(__name__)

SURGICAL_VARIABLES = {
    "tightening": "band circumference shortening (segmental: radial push x 2 pi), mm",
    "buckle_shift": "posterior shift of the fitted buckle along the meridian, mm",
    "buckle_meridian_deg": "meridian of a segmental buckle, degrees",
    "suture_width": "bite span across the buckle, mm",
    "suture_tightening": "shortening of each suture loop when tied, mm",
    "drain_volume": "fluid drained during stage 2, mm^3",
    "band_tension": "tension of a pulled encircling band (cases with band_tension > 0), N",
}
MATERIAL_VARIABLES = {
    **{f"c10_{m}": f"neo-Hookean c10 of the {m.replace('_', ' ')}, MPa" for m in SEED_MATERIALS},
    "zonule_E": "Young's modulus of the zonule, MPa",
    "liquid_bulk": "bulk modulus of the cavity liquid, MPa",
    "suture_EA": "axial stiffness of the sutures, N",
}
DESIGN_VARIABLES = {**SURGICAL_VARIABLES, **MATERIAL_VARIABLES}
STAGE1_VARIABLES = tuple(f"c10_{m}" for m in SEED_MATERIALS) + ("zonule_E",)
"""The design variables that change the pre-operative (pressurised) eye."""
OUTCOMES = {
    "iop_mmhg": "post-operative IOP (cavity pressure), mmHg",
    "indentation_mm": "buckle indentation height, mm",
    "axial_length_change_mm": "axial length change since the pre-operative state, mm",
    "max_suture_force_N": "force in the most loaded suture bar, N",
}


def default_parameters(**overrides) -> dict:
    """Surgery case parameters with defaults (see eyefem.eye.surgery)."""
    p = {f.name: f.default for f in SURGERY_FIELDS}
    unknown = set(overrides) - set(p)
    if unknown:
        raise ValueError(f"unknown surgery parameters {sorted(unknown)}; known: {sorted(p)}")
    p.update(overrides)
    return p


@dataclasses.dataclass
class Preop:
    """The pressurised pre-operative eye of one set of material constants.

    Attributes: sol1 (stage-1 solution), theta2 (params with the cavity closed at its
    volume), scale (snug radial scale of the buckle) and node (the node it touches),
    axial (axial length, mm), materials (the values of STAGE1_VARIABLES)."""

    sol1: Solution
    theta2: dict
    scale: float
    node: int
    axial: float
    materials: tuple


@dataclasses.dataclass
class Result:
    """A converged design: outcome values and the three solutions the adjoint needs."""

    design: dict
    outcomes: dict
    sol2: Solution
    sol3: Solution
    sutures: object  # the suture term of this design
    newton_iterations: int
    preop: Preop | None = None


class SurgerySimulator:
    """Simulate one surgery case for many designs, with warm starts and adjoints.

    Args:
      params: surgery case parameters (eyefem.eye.surgery.SURGERY_FIELDS); the
        design variables in it are the starting design.
      materials: material overrides (name -> MooneyRivlin), as in a case file.
      options: Newton options.
    """

    def __init__(self, params: dict, materials=None, options: NewtonOptions = NewtonOptions()):
        self.params = dict(params)
        self.options = options
        if self.params.get("buckle_body", "rigid") != "rigid":
            raise ValueError(f"buckle_body = '{self.params['buckle_body']}': the design gradients "
                             "and the planner move the rigid buckle's exact surface by its "
                             "parameters; set buckle_body = 'rigid' (a deformable band is "
                             "simulated by `eyefem run` only)")
        setup = surgery(self.params, materials)
        self.setup, self.parts = setup, setup.parts
        self.stage1, self.stage2, self.stage3 = setup.stages
        self.model1 = setup.model
        mesh = self.parts.eye.mesh
        self._mat_row = {m: mesh.materials.index(m) for m in SEED_MATERIALS if m in mesh.materials}
        self._apex, self._pole = mesh.node_set("eye/apex")[0], mesh.node_set("eye/pole")[0]
        sol1 = solve(self.model1, [self.stage1], options=options)
        self.stage1_iterations = sum(r.iterations for r in sol1.history)
        # the buckle and sutures are fitted once, at this eye's snug scale; other designs
        # move them by params
        self.model, _, _ = self.stage2.before(self.model1, sol1.q, sol1.theta)
        self.scale0 = self.parts.scale
        self.meridian0 = float(self.params["buckle_meridian_deg"])
        theta0 = self.model1.theta0()
        self._c10 = {m: float(theta0["solid"]["coeffs"][i, 1, 0]) for m, i in self._mat_row.items()}
        self.preop = self._preop(sol1, self._stage1_key(self.design0()))
        self.last: Result | None = None
        self.pulled = any(t.name == "band_pull" for t in self.model.terms)
        self._ramped = ("solid", "zonule", "buckle", "cavity") + (("band_pull",) if self.pulled else ())

    # --- design -> params ---------------------------------------------------------
    def design0(self) -> dict:
        d = {k: float(self.params[k]) for k in SURGICAL_VARIABLES}
        d.update({f"c10_{m}": c for m, c in self._c10.items()})
        d.update({k: float(self.params[k]) for k in ("zonule_E", "liquid_bulk", "suture_EA")})
        return d

    def _materials_theta(self, theta, design):
        """theta with the design's material constants (solid c10, zonule EA, liquid bulk)."""
        coeffs = np.array(theta["solid"]["coeffs"])
        for m, i in self._mat_row.items():
            coeffs[i, 1, 0] = design[f"c10_{m}"]
        ea = np.full_like(np.asarray(theta["zonule"]["EA"]),
                          design["zonule_E"] * self.parts.eye.geometry.zonule_area)
        cav = theta["cavity"]
        return {**theta, "solid": {**theta["solid"], "coeffs": coeffs},
                "zonule": {**theta["zonule"], "EA": ea},
                "cavity": {**cav, "bulk": np.full_like(np.asarray(cav["bulk"], float),
                                                       design["liquid_bulk"])}}

    def _stage1_key(self, design) -> tuple:
        return tuple(float(design[f"c10_{m}"]) for m in self._mat_row) + (float(design["zonule_E"]),)

    def _preop(self, sol1: Solution, materials: tuple) -> Preop:
        _, _, theta2 = close_cavity(self.model, sol1.q, sol1.theta, "cavity", "iop")
        x = self.parts.eye.mesh.nodes + sol1.q[: 3 * self.parts.eye.mesh.n_nodes].reshape(-1, 3)
        node = snug_node(self.parts, sol1.q)
        return Preop(sol1, theta2, float(snug_scale(self.parts, sol1.q, node)), node,
                     float(np.linalg.norm(x[self._apex] - x[self._pole])), materials)

    def _stage1(self, design) -> Preop:
        """The pre-operative eye for the design's material constants (re-solved from the
        last one, by continuation, when they changed)."""
        want = self._stage1_key(design)
        if want == self.preop.materials:
            return self.preop
        prev = self.preop.sol1
        target = self._materials_theta(prev.theta, design)
        ramp = {k: target[k] for k in ("solid", "zonule")}
        s1 = self.stage1
        try:
            sol1 = solve(self.model1, [Stage(s1.name, 1, s1.prescribed, params=ramp, active=s1.active)],
                         q0=prev.q, theta=prev.theta, options=self.options)
        except ConvergenceError as exc:
            log.warning("pre-operative warm start failed (%s); pressurising again",
                        str(exc).splitlines()[0])
            start = self._materials_theta(self.model1.theta0(), design)
            sol1 = solve(self.model1, [s1], theta=start, options=self.options)
        self.preop = self._preop(sol1, want)
        return self.preop

    def _theta2(self, design, sut, pre: Preop):
        rot = np.full(1, np.radians(design["buckle_meridian_deg"] - self.meridian0))
        dr = np.full(1, self.parts.eye.geometry.scleral_radius * (pre.scale - self.scale0))
        motion = {"d": np.full(1, design["tightening"] * self.parts.d_per_mm),
                  "s": np.full(1, design["buckle_shift"]), "dr": dr, "rot": rot}
        th = self._materials_theta(pre.theta2, design)
        th["buckle"] = {**th["buckle"], **motion, "ridge": self.stage2.params["buckle"]["ridge"]}
        th["sutures"] = {**sut.params, **motion,
                         "EA": np.full_like(sut.params["EA"], design["suture_EA"])}
        th["cavity"] = {**th["cavity"], "dv": -design["drain_volume"]}
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

    def _check(self, design):
        for k in design:
            if k not in DESIGN_VARIABLES:
                raise ValueError(f"unknown design variable '{k}'; known: {sorted(DESIGN_VARIABLES)}")
        d0 = self.design0()
        fixed = ["tightening" if self.pulled else "band_tension"]
        why = {fixed[0]: "its band is pulled by a tension (band_tension > 0); vary band_tension"
               if self.pulled else "its band shortening is prescribed; make a case with "
               "band_tension > 0 and tightening = 0 to vary the tension",
               "buckle_meridian_deg": "an encircling buckle has no meridian (its sutures are "
               "spread evenly around it)"}
        if self.parts.buckle.encircling:
            fixed.append("buckle_meridian_deg")
        for k in fixed:
            if design[k] != d0[k]:
                raise ValueError(f"design variable '{k}' = {design[k]} cannot vary in this "
                                 f"case: {why[k]}")
        for k in MATERIAL_VARIABLES:
            if k in design and not design[k] > 0:
                raise ValueError(f"design variable '{k}' = {design[k]}; a material constant "
                                 "must be > 0")

    # --- forward ------------------------------------------------------------------
    def run(self, design: dict | None = None, *, warm: bool = True) -> Result:
        """Solve the stages for a design (missing variables: the case's values).

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
        self._check(design)
        pre = self._stage1(design)
        sut = suture_term(self.parts, self.scale0, design["suture_width"],
                          design["buckle_meridian_deg"])
        model = self._model(sut)
        held = self.stage2.prescribed
        th2 = self._theta2(design, sut, pre)
        prev = self.last if warm else None
        ramped = {k: th2[k] for k in self._ramped}
        if prev is None:
            start = {**th2, **{k: pre.theta2[k] for k in self._ramped if k not in ("solid", "zonule")}}
            start["cavity"] = {**start["cavity"], "bulk": th2["cavity"]["bulk"]}
            sol2 = solve(model, [Stage("tighten", self.stage2.n_steps, held, params=ramped,
                                       active=self.stage2.active)],
                         q0=pre.sol1.q, theta=start, options=self.options)
        else:
            start = {**prev.sol2.theta, "sutures": th2["sutures"]}
            sol2 = solve(model, [Stage("tighten", 1, held, params=ramped, active=self.stage2.active)],
                         q0=prev.sol2.q, theta=start, options=self.options)
        th3 = self._tied(sut, sol2.q, sol2.theta, design)
        same_faces = prev is not None and np.array_equal(prev.sutures.nodes_a, sut.nodes_a)
        if same_faces:  # continuation of every param from the previous design's state
            sol3 = solve(model, [Stage("suture", 1, self.stage3.prescribed,
                                       params={k: th3[k] for k in self._ramped + ("sutures",)},
                                       active=self.stage3.active)],
                         q0=prev.sol3.q, theta=prev.sol3.theta, options=self.options)
        else:
            untied = {**th3, "sutures": {**th3["sutures"], "tightening": 0 * th3["sutures"]["tightening"]}}
            sol3 = solve(model, [Stage("suture", self.stage3.n_steps, self.stage3.prescribed,
                                       params={"sutures": th3["sutures"]},
                                       active=self.stage3.active)],
                         q0=sol2.q, theta=untied, options=self.options)
        its = sum(r.iterations for r in sol2.history + sol3.history)
        res = Result(design, {}, sol2, sol3, sut, its, pre)
        res.outcomes = {k: float(f(sol3.q, sol3.theta)) for k, f in self.outcome_fns(res).items()}
        self.last = res
        return res

    # --- outcomes as JAX functions ---------------------------------------------------
    def outcome_fns(self, res: Result) -> dict[str, Callable]:
        """Outcome name -> J(q, theta), JAX-traceable, at the converged design ``res``
        (the axial length change from ``res``'s own pre-operative axial length)."""
        from eyefem.eye.surgery import _buckle_coords

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
        axial_preop = (res.preop or self.preop).axial

        def x_of(q, ids):
            return X[ids] + q[: 3 * mesh.n_nodes].reshape(-1, 3)[ids]

        def iop(q, theta):
            P, _, _, _ = cavity_state(q, theta["cavity"], cav.data, cav.dofs)
            return P[0] / MMHG

        def indentation(q, theta):
            r = lambda ids: jnp.mean(jnp.linalg.norm(x_of(q, ids), axis=1))  # noqa: E731
            return r(beside) - r(under)

        def axial(q, theta):
            x = x_of(q, np.array([self._apex, self._pole]))
            return jnp.linalg.norm(x[0] - x[1]) - axial_preop

        def suture_force(q, theta):
            return sut.axial_forces(q[sut.dofs], theta["sutures"], sut.data)[i_max]

        return {"iop_mmhg": iop, "indentation_mm": indentation, "axial_length_change_mm": axial,
                "max_suture_force_N": suture_force}

    # --- adjoint ------------------------------------------------------------------
    def gradients(self, res: Result, outcomes=None) -> dict[str, dict[str, float]]:
        """d outcome / d design variable for the named outcomes (default: all OUTCOMES)."""
        fns = self.outcome_fns(res)
        names = list(OUTCOMES) if outcomes is None else list(outcomes)
        dxi_w = self._dxi(res, "suture_width")
        dxi_m = self._dxi(res, "buckle_meridian_deg") if not self.parts.buckle.encircling else None
        sut, pre = res.sutures, res.preop or self.preop
        rs = self.parts.eye.geometry.scleral_radius
        area = self.parts.eye.geometry.zonule_area
        out = {}
        for name in names:
            _, g3 = value_and_grad(fns[name], res.sol3)
            gL0 = jnp.asarray(g3["sutures"]["L0"])

            def tied_length(q, theta):
                return jnp.dot(gL0, sut.lengths(q[sut.dofs], theta["sutures"], sut.data))

            _, g2 = value_and_grad(tied_length, res.sol2)
            g1 = self._preop_adjoint(pre, sum(float(np.sum(g["cavity"]["v_ini"])) for g in (g2, g3)),
                                     rs * sum(float(np.sum(g[t]["dr"])) for g in (g2, g3)
                                              for t in ("buckle", "sutures")),
                                     -1.0 if name == "axial_length_change_mm" else 0.0)

            def total(term, key, gs=(g2, g3)):
                return sum(np.sum(g[term][key]) for g in gs)

            def bites(dxi):
                return float(sum(np.sum(np.asarray(g["sutures"]["xi"]) * dxi) for g in (g2, g3)))

            d = {
                "tightening": self.parts.d_per_mm * (total("buckle", "d") + total("sutures", "d")),
                "buckle_shift": total("buckle", "s") + total("sutures", "s"),
                "buckle_meridian_deg": 0.0 if dxi_m is None else
                np.pi / 180 * (total("buckle", "rot") + total("sutures", "rot")) + bites(dxi_m),
                "suture_width": bites(dxi_w),
                "suture_tightening": 0.5 * float(np.sum(g3["sutures"]["tightening"])),
                "drain_volume": -total("cavity", "dv"),
                "band_tension": total("band_pull", "f") if self.pulled else 0.0,
                "zonule_E": area * total("zonule", "EA", (g1, g2, g3)),
                "liquid_bulk": total("cavity", "bulk"),
                "suture_EA": total("sutures", "EA"),
            }
            for m, i in self._mat_row.items():
                d[f"c10_{m}"] = sum(float(np.asarray(g["solid"]["coeffs"])[i, 1, 0]) for g in (g1, g2, g3))
            out[name] = {k: float(d.get(k, 0.0)) for k in DESIGN_VARIABLES}
        return out

    def _preop_adjoint(self, pre: Preop, g_volume, g_scale, g_axial):
        """Stage-1 adjoint: d/dtheta_1 of g_volume V(q1) + g_scale s(q1) + g_axial a(q1),
        the routes by which the pre-operative eye enters the later stages and outcomes."""
        cav, mesh = self.model.term("cavity"), self.parts.eye.mesh
        ends = np.array([self._apex, self._pole])

        def preop(q, theta):
            V = cavity_pressures(q, theta["cavity"], cav.data, cav.dofs)[1][0]
            x = mesh.nodes[ends] + q[: 3 * mesh.n_nodes].reshape(-1, 3)[ends]
            return (g_volume * V + g_scale * snug_scale(self.parts, q, pre.node)
                    + g_axial * jnp.linalg.norm(x[0] - x[1]))

        return value_and_grad(preop, pre.sol1)[1]

    def _dxi(self, res: Result, var: str, h: float = 1e-4):
        """d xi / d var (n_bars, 2) of the bites (var: suture_width or buckle_meridian_deg),
        by central differences of the suture geometry (no simulation; one-sided where a
        bite changes face within +-h)."""
        w, m = res.design["suture_width"], res.design["buckle_meridian_deg"]
        lay = [suture_layout(self.parts, w + e, m) if var == "suture_width"
               else suture_layout(self.parts, w, m + e) for e in (-h, 0.0, h)]
        xi = [np.concatenate([x.bite_a.xi, x.bite_b.xi]) for x in lay]
        nd = [np.concatenate([x.bite_a.nodes, x.bite_b.nodes]) for x in lay]
        out = (xi[2] - xi[0]) / (2 * h)
        for i in range(len(out)):
            same_m, same_p = np.array_equal(nd[0][i], nd[1][i]), np.array_equal(nd[2][i], nd[1][i])
            if not (same_m and same_p):
                out[i] = (xi[2][i] - xi[1][i]) / h if same_p else (xi[1][i] - xi[0][i]) / h
        return out

"""Surgical design variables: warm-started simulation of designs; their adjoint gradients
(eyefem.eye.sensitivity).

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

with G_V, G_s the totals of g_2 + g_3 over v_ini and dr and G_a the outcome's own
dependence on the pre-operative eye (the changes measured from it: axial length,
refraction, ...; eyefem.eye.sensitivity); then chained through the maps T_k, written
once as a JAX function of the design (SurgerySimulator.design_map) and differentiated
by jax.vjp, the suture bites by their exact derivative within their faces
(eyefem.eye.sutures.radial_bite_sensitivity). So the history of the load path (sutures tied on
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

from eyefem.eye.outcomes import changes, eye_optics, indentation, outcome_nodes
from eyefem.eye.parts import snug_node, snug_scale
from eyefem.eye.presets import SEED_MATERIALS
from eyefem.eye.rigid_buckle import suture_term
from eyefem.eye.sensitivity import DesignGradients, term_kind
from eyefem.eye.surgery import surgery
from eyefem.eye.variables import (  # noqa: F401 - the design's names, re-exported
    DESIGN_VARIABLES,
    MATERIAL_PARAMS,
    MATERIAL_VARIABLES,
    OPTICAL_CHANGES,
    OUTCOMES,
    STAGE1_VARIABLES,
    STAGE_PARAMS,
    SURGICAL_VARIABLES,
    default_parameters,
)
from eyefem.fem.cavity import cavity_state, close_cavity
from eyefem.fem.units import MMHG
from eyefem.solve.solver import ConvergenceError, NewtonOptions, Solution, Stage, solve

log = logging.getLogger(__name__)

@dataclasses.dataclass
class Preop:
    """The pressurised pre-operative eye of one set of material constants.

    Attributes: sol1 (stage-1 solution), theta2 (params with the cavity closed at its
    volume), scale (snug radial scale of the buckle) and node (the node it touches),
    optics (eyefem.eye.outcomes.eye_optics: axial length, corneal power, ...),
    materials (the values of STAGE1_VARIABLES)."""

    sol1: Solution
    theta2: dict
    scale: float
    node: int
    optics: dict
    materials: tuple

    @property
    def axial(self) -> float:
        """Pre-operative axial length, mm."""
        return self.optics["axial_length_mm"]


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


class SurgerySimulator(DesignGradients):
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
        self._nodes = outcome_nodes(self.parts)
        self._compiled: dict = {}  # outcome functions, one per outcome list (outcome_vector)
        sol1 = _kept(solve(self.model1, [self.stage1], options=options))
        self.stage1_iterations = sum(r.iterations for r in sol1.history)
        # the buckle and sutures are fitted once, at this eye's snug scale; other designs
        # move them by params
        self.model, _, _ = self.stage2.before(self.model1, sol1.q, sol1.theta)
        self.scale0 = float(snug_scale(self.parts, sol1.q))
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

    def design_map(self, design: dict, like: dict, bites=None) -> dict:
        """The stage params the design variables set: term -> param -> array, shaped like
        the params of the theta ``like``; a JAX function of ``design`` (name -> scalar), the
        one map from the design to the model that the forward run evaluates and the
        adjoint differentiates (jax.vjp, eyefem.eye.sensitivity).

        buckle and sutures: d = tightening x d_per_mm (radial motion), s = buckle_shift,
        rot = meridian - the case's meridian (radians); sutures: EA, tightening =
        suture_tightening / 2 per bar (stage 3), and with ``bites`` = (xi (n, 2), dxi/dw,
        dxi/dmeridian, w, meridian) the bites xi linearised about that design (the exact
        derivative of the layout there); cavity: dv = -drain_volume, bulk; zonule: EA =
        zonule_E x its area; solid: c10 of each tissue; band_pull: f = band_tension.
        Not here: the buckle's radial fit dr, set by the pre-operative eye (stage 1)."""
        def full(term, key, v):
            return jnp.broadcast_to(jnp.asarray(v, dtype=jnp.float64), np.shape(like[term][key]))

        rot = (design["buckle_meridian_deg"] - self.meridian0) * (np.pi / 180)
        motion = {"d": design["tightening"] * self.parts.d_per_mm, "s": design["buckle_shift"],
                  "rot": rot}
        rows = np.array(list(self._mat_row.values()))
        c10 = jnp.stack([jnp.asarray(design[f"c10_{m}"], jnp.float64) for m in self._mat_row])
        out = {"buckle": {k: full("buckle", k, v) for k, v in motion.items()},
               "sutures": {**{k: full("sutures", k, v) for k, v in motion.items()},
                           "EA": full("sutures", "EA", design["suture_EA"]),
                           "tightening": full("sutures", "tightening",
                                              design["suture_tightening"] / 2)},
               "cavity": {"dv": full("cavity", "dv", -design["drain_volume"]),
                          "bulk": full("cavity", "bulk", design["liquid_bulk"])},
               "zonule": {"EA": full("zonule", "EA",
                                     self.parts.eye.zonule_bar_EA(design["zonule_E"]))},
               "solid": {"coeffs": jnp.asarray(like["solid"]["coeffs"]).at[rows, 1, 0].set(c10)}}
        if self.pulled:
            out["band_pull"] = {"f": full("band_pull", "f", design["band_tension"])}
        if bites is not None:
            xi, dxi_w, dxi_m, w, m = bites
            out["sutures"]["xi"] = (xi + dxi_w * (design["suture_width"] - w)
                                    + dxi_m * (design["buckle_meridian_deg"] - m))
        return out

    def _with_design(self, theta, design, keys) -> dict:
        """theta with the design's values (design_map) of ``keys`` ((term, param) pairs)."""
        values = self.design_map(design, theta)
        out = dict(theta)
        for term, key in keys:
            out[term] = {**out[term], key: np.asarray(values[term][key])}
        return out

    def _materials_theta(self, theta, design):
        """theta with the design's material constants (solid c10, zonule EA, liquid bulk)."""
        return self._with_design(theta, design, MATERIAL_PARAMS + (("cavity", "bulk"),))

    def _stage1_key(self, design) -> tuple:
        return tuple(float(design[f"c10_{m}"]) for m in self._mat_row) + (float(design["zonule_E"]),)

    def _preop(self, sol1: Solution, materials: tuple) -> Preop:
        _, _, theta2 = close_cavity(self.model, sol1.q, sol1.theta, "cavity", "iop")
        node = snug_node(self.parts, sol1.q)
        optics = {k: float(v) for k, v in eye_optics(self.parts.eye.mesh.nodes, sol1.q,
                                                     self._nodes).items()}
        return Preop(sol1, theta2, float(snug_scale(self.parts, sol1.q, node)), node, optics,
                     materials)

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
            sol1 = _kept(solve(self.model1, [Stage(s1.name, 1, s1.prescribed, params=ramp,
                                                   active=s1.active)],
                               q0=prev.q, theta=prev.theta, options=self.options))
        except ConvergenceError as exc:
            log.warning("pre-operative warm start failed (%s); pressurising again",
                        str(exc).splitlines()[0])
            start = self._materials_theta(self.model1.theta0(), design)
            sol1 = _kept(solve(self.model1, [s1], theta=start, options=self.options))
        self.preop = self._preop(sol1, want)
        return self.preop

    def _theta2(self, design, sut, pre: Preop):
        """Stage 2's params: the design's (design_map) on the closed pre-operative eye, the
        buckle and sutures fitted at its snug scale (dr)."""
        dr = np.full(1, self.parts.eye.geometry.scleral_radius * (pre.scale - self.scale0))
        th = {**pre.theta2, "sutures": sut.params,
              "buckle": {**pre.theta2["buckle"], "dr": dr,
                         "ridge": self.stage2.params["buckle"]["ridge"]}}
        th["sutures"] = {**th["sutures"], "dr": dr}
        keys = [k for k in STAGE_PARAMS[2] if k[0] in th and k != ("sutures", "xi")]
        return self._with_design(th, design, keys)

    def _tied(self, sut, q2, theta2, design):
        """Stage 3's params: the sutures tied at their stage-2 lengths and tightened."""
        L = np.asarray(sut.lengths(np.asarray(q2)[sut.dofs], theta2["sutures"], sut.data))
        th = {**theta2, "sutures": {**theta2["sutures"], "L0": L}}
        return self._with_design(th, design, [("sutures", "tightening")])

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
        sol2 = _kept(sol2)
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
        sol3 = _kept(sol3)
        its = sum(r.iterations for r in sol2.history + sol3.history)
        res = Result(design, {}, sol2, sol3, sut, its, pre)
        f, data = self.outcome_vector(res, OUTCOMES)
        res.outcomes = dict(zip(OUTCOMES, map(float, f(sol3.q, sol3.theta, data))))
        self.last = res
        return res

    # --- outcomes as JAX functions ---------------------------------------------------
    def outcome_vector(self, res: Result, names, weights=None) -> tuple[Callable, dict]:
        """(f, data): f(q, theta, data) -> (k,) the named outcomes at the converged design
        ``res`` (the changes measured from ``res``'s own pre-operative eye;
        eyefem.eye.outcomes), the eye's optics evaluated once for all of them; with
        ``weights`` (k,), (1,) their weighted sum. f is a function of its arguments alone,
        one object per outcome list and kind of suture term, so that its derivatives are
        compiled once for every design (eyefem.solve.adjoint.values_and_grads); ``data``
        holds what belongs to ``res``: the pre-operative optics, the cavity's and the
        sutures' data, the bar of the largest suture force."""
        names, sut = tuple(names), res.sutures
        f = self._kept_fn(("outcomes", names, weights is None, term_kind(sut)),
                          lambda: self._outcome_vector_fn(names, sut))
        cav = res.sol3.model.term("cavity")
        force = np.asarray(sut.forces(res.sol3.q, res.sol3.theta["sutures"]))
        data = {"preop": {k: jnp.asarray(v, jnp.float64)
                          for k, v in (res.preop or self.preop).optics.items()},
                "cavity": (cav.data, cav.dofs), "sutures": (sut.data, sut.dofs),
                "largest": jnp.asarray(int(np.argmax(force))),
                "weights": None if weights is None else jnp.asarray(weights, jnp.float64)}
        return f, data

    def _outcome_vector_fn(self, names: tuple, sut) -> Callable:
        """f(q, theta, data) of :meth:`outcome_vector` (``sut``: a suture term of the kind
        whose data f receives; only its methods are used)."""
        X, nodes = self.parts.eye.mesh.nodes, self._nodes
        optical = set(OPTICAL_CHANGES) | {"corneal_astigmatism_D"}

        def outcome(name, q, theta, data, opt, ch):
            if name in OPTICAL_CHANGES:
                return ch[name]
            if name in optical:
                return opt[name]
            if name == "iop_mmhg":
                return cavity_state(q, theta["cavity"], *data["cavity"])[0][0] / MMHG
            if name == "indentation_mm":
                return indentation(X, q, nodes)
            if name == "max_suture_force_N":
                sut_data, sut_dofs = data["sutures"]
                return sut.axial_forces(q[sut_dofs], theta["sutures"], sut_data)[data["largest"]]
            raise KeyError(f"unknown outcome '{name}'; known: {list(OUTCOMES)}")

        def outcomes(q, theta, data):
            opt = eye_optics(X, q, nodes) if optical & set(names) else None
            ch = changes(opt, data["preop"]) if opt is not None else {}
            values = jnp.stack([outcome(n, q, theta, data, opt, ch) for n in names])
            w = data["weights"]
            return values if w is None else jnp.reshape(jnp.dot(w, values), (1,))

        return outcomes

    def outcome_fns(self, res: Result) -> dict[str, Callable]:
        """Outcome name -> J(q, theta), JAX-traceable, at the converged design ``res`` (one
        outcome of :meth:`outcome_vector` each)."""
        def one(name):
            f, data = self.outcome_vector(res, (name,))
            return lambda q, theta: f(q, theta, data)[0]

        return {name: one(name) for name in OUTCOMES}


def _kept(sol: Solution) -> Solution:
    """``sol`` with its last factorisation kept out of the Pardiso instance its sparsity
    pattern shares (SaddlePointSolver.keep): the stages of a surgery share one pattern,
    and the design gradients solve on each stage's factorisation after the later stages
    have factorised; kept, none is factorised again for the gradients."""
    if sol.solver is not None:
        sol.solver.keep()
    return sol

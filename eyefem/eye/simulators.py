"""The design simulators: warm-started simulation of designs and their adjoint gradients.

The design of a surgery case is a dict of continuous variables (DESIGN_VARIABLES,
eyefem.eye.variables; eyefem.eye.design re-exports them with these simulators): the
surgical ones (band tightening or tension, buckle shift and meridian, suture width and
tightening, drained volume) and material constants (MATERIAL_VARIABLES: c10 of every
tissue, the zonule's Young's modulus, the liquid's bulk modulus, the sutures' EA) for
sensitivity studies. The rigid-buckle procedure is three stages, each an equilibrium
R_k(q_k, theta_k) = 0 whose params are functions of the design and of what the earlier
stages hand on (eyefem.solve.staged.StageMap, written once in JAX):

    theta_1 = T_1(design)                                   (pressurise; materials only)
    theta_2 = T_2(design, V, s),   (V, s, optics) = C_1(q_1) (tighten / place)
    theta_3 = T_3(design, V, s, L0),         L0 = C_2(q_2, theta_2)     (suture)

with V the cavity volume at which it is closed, s the snug radial scale of the fitted
buckle (params "dr" of the buckle and its sutures), the pre-operative optics that the
changes are measured from, and L0 the tied suture lengths. The carries are the buckle
bodies' (eyefem.eye.bodies.preop_carry; tied_lengths, the rule by which ``eyefem run``'s
suture stage ties the sutures, tie_sutures). The forward run sets each stage's params from
T_k and hands C_k on; the gradient of the outcomes
(eyefem.eye.outcomes.outcome_function) differentiates the same functions by one backward
sweep (eyefem.solve.staged.staged_gradients: one adjoint solve per stage on its last
Newton factorisation, a jax.vjp through each T_k and C_k). The suture bites are a JAX
function of the suture width and meridian inside T_2 / T_3
(eyefem.eye.rigid_buckle.BiteRays). So the history of the load path (sutures tied on the
tightened eye, buckle fitted on the inflated eye) is differentiated, not frozen. The
contact state (which nodes touch) is smooth (buckle_contact), so the response is smooth
in the design except where a suture bite crosses a face boundary of the sclera (the bite
stays continuous; its derivative jumps) or the snug buckle's touching node changes - see
docs/adjoint.md.

The buckle and sutures are fitted once, on the case's own pre-operative eye and at its
meridian; a design moves them by params (shift, radial fit "dr", turn "rot" about the
eye axis), so every outcome is measured at the case's buckle position (the retinal
break): a moved buckle indents less there.

A case on the surgery's timeline (volume_regulation = true, eyefem.eye.timeline) is
simulated by :class:`TimelineSimulator` (``SurgerySimulator(params)`` of such a case is
one): every step after the closing is one stage of the staged adjoint, its carry the
cavity's history, its IOP and where needed the optics, so that the timeline's outcomes
(the peak IOP on the table, the minutes above the central retinal artery's closing
pressure, the IOP and the shape at the follow-up times) and their gradients in the design
(the paracentesis's volume and time among its variables) come from one backward sweep.

:class:`SurgerySimulator`, :class:`TimelineSimulator` and :class:`RingSimulator` (a
deformable band or tire, its T_2 / T_3 eyefem.eye.bodies.DeformableRing.design_params)
share the outcomes of a converged design and their gradients (:class:`StagedSimulator`).

A rigid-buckle case with ``symmetry = 'mirror'`` (eyefem.eye.mirror) is simulated on its
mirror half: the buckle and sutures fitted on the whole eye, the stages solved on the
half, T_k's params halved where the half's are (the cavity's volumes), C_k and the
outcomes evaluated on the lifted whole state, so the same backward sweep gives the whole
eye's gradients; a segmental buckle's meridian is then fixed (turned off the plane, the
buckle breaks the symmetry).

Warm start: ``run(design, start=result)`` solves a design from another design's converged
states, by continuation of the params in one step (cut automatically if needed); the
equilibria do not depend on the path (hyperelastic, frictionless). Stage 1 is solved
again only when a material constant changes.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.eye.bodies import DeformableRing, preop_carry, tied, tied_lengths
from eyefem.eye.mirror import half_term, mirror_of, mirror_setup, theta_half, theta_whole
from eyefem.eye.outcomes import (cavity_pressure, changes, eye_optics, indentation,
                                 outcome_data, outcome_data_of, outcome_function, outcome_nodes)
from eyefem.eye.parts import snug_node, snug_scale
from eyefem.eye.presets import SEED_MATERIALS
from eyefem.eye.rigid_buckle import BiteRays, bite_rays, rigid_design_params, suture_term
from eyefem.eye.surgery import surgery
from eyefem.eye.variables import (
    DESIGN_VARIABLES,
    MATERIAL_VARIABLES,
    OUTCOMES,
    SURGICAL_VARIABLES,
    TIMELINE_VARIABLES,
)
from eyefem.eye import timeline
from eyefem.fem.cavity import close_cavity
from eyefem.fem.regulation import HISTORY_KEYS, advanced_history
from eyefem.fem.units import MMHG
from eyefem.fem.viscoelastic import ViscoelasticQ1P0, history_at
from eyefem.solve.assembly import Assembler
from eyefem.solve.model import Model
from eyefem.solve.solver import ConvergenceError, NewtonOptions, Solution, Stage, solve
from eyefem.solve.staged import (StageMap, StageRecord, compiled, hand_on, params_mismatch,
                                 stage_params, staged_gradients)
from eyefem.solve.transient import Recorder

log = logging.getLogger(__name__)

WARM_START_LIMITS = {"max_iter": 20, "max_cuts": 2, "stall_cut": True}
"""Newton's limits for a warm start (a design continued from another design's converged
state in one load step: ``run(design, start=result)``): at most 20 iterations a step, a
stalled step cut at once, 2 halvings; a continuation that needs more costs more than the
load path from the pre-operative eye, which :meth:`SurgerySimulator.run` then solves (a
stalled continuation on `fine` can otherwise iterate for many minutes under the case's own
limits)."""


def term_kind(term) -> tuple:
    """The key of the compiled functions of a term's state, one per kind whatever the
    design: its class and static configuration, as the model's kernels are keyed
    (eyefem.solve.model.Model._kernel: its methods read arrays only from their arguments)."""
    return (type(term), term.static_key())


@dataclasses.dataclass(frozen=True)
class Preop:
    """The pressurised pre-operative eye of one set of material constants.

    Attributes: sol1 (stage-1 solution), theta2 (params with the cavity closed at its
    volume), node (the node the snug buckle touches), carry (what stage 1 hands on:
    "volume" (mm^3), "scale" (the buckle's snug radial scale), "optics"
    (eyefem.eye.outcomes.eye_optics)), materials (the values of STAGE1_VARIABLES)."""

    sol1: Solution
    theta2: dict
    node: int
    carry: dict
    materials: tuple

    @property
    def optics(self) -> dict:
        """The pre-operative optics, floats (axial length, mm, ...)."""
        return {k: float(v) for k, v in self.carry["optics"].items()}

    @property
    def scale(self) -> float:
        """The snug radial scale of the buckle on this eye."""
        return float(self.carry["scale"])

    @property
    def axial(self) -> float:
        """Pre-operative axial length, mm."""
        return self.optics["axial_length_mm"]


@dataclasses.dataclass(frozen=True)
class Prepared:
    """What a run of one design starts from (:meth:`SurgerySimulator._prepared`).

    Attributes:
      design: the design, the case's values filled in and checked (name -> float).
      preop: the pre-operative eye of its material constants.
      sutures: its suture term (bites on the faces its width and meridian give).
      model: the stage-2 model with that suture term (on the mirror half, its half).
      bites: the bites' rays (BiteRays), of which T_2 places the bites.
      maps: the stages as data (pressurise, tighten, suture: StageMap).
      theta2: stage 2's params, T_2 on the closed pre-operative eye.
      ramped: the params stage 2 ramps to (term -> params).
      start: stage 2's params at its start (the ramped ones at their pre-operative values).
    """

    design: dict
    preop: Preop
    sutures: object
    model: Model
    bites: BiteRays
    maps: tuple
    theta2: dict
    ramped: dict
    start: dict


@dataclasses.dataclass(frozen=True)
class Result:
    """A converged design: outcome values, its stages (eyefem.solve.staged.StageRecord:
    pressurise, tighten, suture) and the suture term and bites of its layout."""

    design: dict
    outcomes: dict
    stages: tuple
    sutures: object  # the suture term of this design
    bites: BiteRays
    newton_iterations: int
    preop: Preop

    @property
    def sol2(self) -> Solution:
        return self.stages[1].solution

    @property
    def sol3(self) -> Solution:
        return self.stages[2].solution


class StagedSimulator:
    """What the design simulators share (:class:`SurgerySimulator`, its
    :class:`TimelineSimulator` and :class:`RingSimulator`): the compiled functions kept
    per kind, the outcomes of a converged design's last stage and their gradients by one
    backward sweep over its stages (eyefem.solve.staged.staged_gradients). A subclass sets
    ``params``, ``parts``, ``_nodes`` (eyefem.eye.outcomes.OutcomeNodes), ``_compiled``
    ({}), and runs designs into results with ``design``, ``stages`` (the last one's
    solution: the converged design) and ``sutures`` (its suture term). A run depends on its
    design and on the result it is told to start from (``run(design, start=...)``), never
    on which designs the simulator solved before."""

    outcome_names = tuple(OUTCOMES)
    """The outcomes run() reports and gradients() differentiates, in order."""
    variables: tuple = tuple(DESIGN_VARIABLES)
    """The design variables gradients() differentiates in."""

    def _kept_fn(self, key, build: Callable):
        """The object cached under ``key`` (built by ``build()`` the first time)."""
        if key not in self._compiled:
            self._compiled[key] = build()
        return self._compiled[key]

    def outcome_vector(self, res, names, weights=None) -> tuple[Callable, dict]:
        """(f, data): f(q, theta, carry, data) -> (k,) the named outcomes at the converged
        design ``res`` (eyefem.eye.outcomes.outcome_function: the changes measured from
        the carried pre-operative optics); with ``weights`` (k,), (1,) their weighted sum.
        f is one object per outcome list and kind of suture term, so that its derivatives
        are compiled once for every design; ``data`` holds what belongs to ``res``
        (eyefem.eye.outcomes.outcome_data)."""
        names, sut, sol = tuple(names), res.sutures, res.stages[-1].solution
        f = self._kept_fn(("outcomes", names, term_kind(sut)),
                          lambda: outcome_function(names, sol.model.mesh.nodes, self._nodes,
                                                   sut))
        return f, outcome_data(sol.model, sol.q, sol.theta, weights)

    def _evaluated(self, res, q, theta, carry):
        """``res`` with its outcomes (:attr:`outcome_names`) at its last state (q, theta)
        and the carries its stages handed on."""
        f, data = self.outcome_vector(res, self.outcome_names)
        values = compiled(f)(jnp.asarray(q), theta, carry, data)
        return dataclasses.replace(res, outcomes=dict(zip(self.outcome_names,
                                                          map(float, values))))

    def gradients(self, res, outcomes=None) -> dict[str, dict[str, float]]:
        """d outcome / d design variable for the named outcomes (default: every one of
        :attr:`outcome_names`): one backward sweep over the stages
        (eyefem.solve.staged.staged_gradients), one right-hand side per outcome."""
        names = list(self.outcome_names) if outcomes is None else list(outcomes)
        return dict(zip(names, self._gradients(res, *self.outcome_vector(res, names))))

    def weighted_gradient(self, res, weights: dict) -> dict[str, float]:
        """d (sum_k w_k outcome_k) / d design variable, for outcome name -> weight w_k: the
        cost of one outcome's gradient whatever the weights (the backward pass of
        eyefem.simulate)."""
        items = [(k, float(w)) for k, w in weights.items() if w]
        if not items:
            return {k: 0.0 for k in self.variables}
        names = [k for k, _ in items]
        w = np.array([w for _, w in items])
        return self._gradients(res, *self.outcome_vector(res, names, w))[0]

    def _gradients(self, res, f, data) -> list[dict[str, float]]:
        """The design gradients of the objectives f (one dict per objective)."""
        return staged_gradients(res.stages, res.design, f, data)[1]


class SurgerySimulator(StagedSimulator):
    """Simulate one rigid-buckle surgery case for many designs, with warm starts and
    adjoint gradients.

    Args:
      params: surgery case parameters (eyefem.eye.surgery.SURGERY_FIELDS); the
        design variables in it are the starting design.
      materials: material overrides (name -> MooneyRivlin), as in a case file.
      options: Newton options.
    """

    def __new__(cls, params: dict, *args, **kwargs):
        # a case on the surgery's timeline is simulated by its own class (same interface)
        if cls is SurgerySimulator and dict(params).get("volume_regulation", False):
            cls = TimelineSimulator
        return super().__new__(cls)

    halves = True
    """Whether a case with ``symmetry = 'mirror'`` is simulated on its mirror half
    (:class:`TimelineSimulator`: the whole eye)."""

    def __init__(self, params: dict, materials=None, options: NewtonOptions = NewtonOptions()):
        half = self.halves and params.get("symmetry", "none") == "mirror"
        self.params = dict(params) if half else whole_eye(params)
        self.options = options
        if self.params.get("buckle_body", "rigid") != "rigid":
            raise ValueError(f"buckle_body = '{self.params['buckle_body']}': the design gradients "
                             "and the planner move the rigid buckle's exact surface by its "
                             "parameters; set buckle_body = 'rigid' (a deformable band or "
                             "tire: RingSimulator)")
        whole = surgery({**self.params, "symmetry": "none"}, materials)
        self.parts = whole.parts
        self.mir = mirror_of(whole.model) if half else None
        setup = whole if self.mir is None else mirror_setup(whole, mir=self.mir)
        self.setup = setup
        # pressurise, tighten (or place), suture (on the timeline, more stages between)
        self.stage1, self.stage2 = setup.stages[:2]
        self.stage3 = next(s for s in setup.stages if s.name == "suture")
        self.model1 = setup.model
        mesh = self.parts.eye.mesh
        self._mat_row = {m: mesh.materials.index(m) for m in SEED_MATERIALS if m in mesh.materials}
        self._nodes = outcome_nodes(self.parts)
        self._compiled: dict = {}  # outcome and carry functions, one per kind (outcome_vector)
        sol1 = _lean(solve(self.model1, [self.stage1], options=options))
        self.stage1_iterations = sum(r.iterations for r in sol1.history)
        # the buckle and sutures are fitted once, at this eye's snug scale; other designs
        # move them by params
        self.model, _, _ = self.stage2.before(self.model1, sol1.q, sol1.theta)
        # the whole eye's cavity (its carries and outcomes are the whole eye's)
        self._cavity = (self.model if self.mir is None
                        else setup.whole.lift(self.model, sol1.q, sol1.theta)[0]).term("cavity")
        self.scale0 = float(snug_scale(self.parts, self._lifted(sol1.q)))
        self.meridian0 = float(self.params["buckle_meridian_deg"])
        theta0 = self.model.theta0()
        self._shapes = {t: {k: np.shape(v) for k, v in ps.items()} for t, ps in theta0.items()}
        self._coeffs = np.asarray(theta0["solid"]["coeffs"])
        self._c10 = {m: float(self._coeffs[i, 1, 0]) for m, i in self._mat_row.items()}
        self.pulled = any(t.name == "band_pull" for t in self.model.terms)
        self._ramped = ("solid", "zonule", "buckle", "cavity") + (("band_pull",) if self.pulled else ())
        # the case's pre-operative eye, never replaced: a design of other material constants
        # continues from it, or from its start result's (_stage1)
        self.preop = self._preop(sol1, self._stage1_key(self.design0()))

    # --- the procedure as data: design -> params, what each stage hands on ----------
    def design0(self) -> dict:
        d = {k: float(self.params[k]) for k in SURGICAL_VARIABLES}
        d.update({f"c10_{m}": c for m, c in self._c10.items()})
        d.update({k: float(self.params[k]) for k in ("zonule_E", "liquid_bulk", "suture_EA")})
        return d

    def _full(self, term, key, v):
        return jnp.broadcast_to(jnp.asarray(v, dtype=jnp.float64), self._shapes[term][key])

    def _materials(self, design) -> dict:
        """T_1: the params of the design's material constants (solid c10, zonule EA)."""
        rows = np.array(list(self._mat_row.values()))
        c10 = jnp.stack([jnp.asarray(design[f"c10_{m}"], jnp.float64) for m in self._mat_row])
        return {"solid": {"coeffs": jnp.asarray(self._coeffs).at[rows, 1, 0].set(c10)},
                "zonule": {"EA": self._full("zonule", "EA",
                                            self.parts.eye.zonule_bar_EA(design["zonule_E"]))}}

    def design_map(self, design: dict, carry: dict, bites: BiteRays) -> dict:
        """T_2: the params of stage 2 (term -> param -> array, JAX) from the design (name
        -> scalar) and stage 1's carry: the rigid buckle's own params
        (eyefem.eye.rigid_buckle.rigid_design_params: radial motion d, shift s, drained
        volume, band tension) and rot = meridian - the case's meridian (radians),
        dr = R (s - s_0) the radial fit on this pre-operative eye (s its snug scale, s_0
        the one the terms were fitted at); sutures: EA, the bites xi (``bites``, a
        function of suture_width and the meridian); cavity: v_ini = the volume at
        closure, bulk; zonule: EA = zonule_E x its area; solid: c10 of each tissue."""
        rot = (design["buckle_meridian_deg"] - self.meridian0) * (np.pi / 180)
        dr = self.parts.eye.geometry.scleral_radius * (carry["scale"] - self.scale0)
        tighten, _ = rigid_design_params(self.parts, design)
        motion = {**tighten["buckle"], "rot": rot, "dr": dr}
        full = self._full
        out = {"buckle": {k: full("buckle", k, v) for k, v in motion.items()},
               "sutures": {**{k: full("sutures", k, v) for k, v in motion.items()},
                           "EA": full("sutures", "EA", design["suture_EA"]),
                           "xi": bites.xi_of(design["suture_width"],
                                             design["buckle_meridian_deg"])},
               "cavity": {"v_ini": full("cavity", "v_ini", carry["volume"]),
                          "dv": full("cavity", "dv", tighten["cavity"]["dv"]),
                          "bulk": full("cavity", "bulk", design["liquid_bulk"])},
               **self._materials(design)}
        if "band_pull" in tighten:
            out["band_pull"] = {"f": full("band_pull", "f", tighten["band_pull"]["f"])}
        return out

    def _tied(self, design, carry, bites) -> dict:
        """T_3: stage 2's params (design_map) with the sutures tied at their stage-2
        lengths L0 and shortened (eyefem.eye.rigid_buckle.rigid_design_params)."""
        out = self.design_map(design, carry, bites)
        _, suture = rigid_design_params(self.parts, design)
        out["sutures"] = tied({**out["sutures"], "tightening": self._full(
            "sutures", "tightening", suture["sutures"]["tightening"])},
            self._full("sutures", "L0", carry["L0"]))
        return out

    def maps(self, sut) -> tuple[StageMap, StageMap, StageMap]:
        """The three stages as data (eyefem.solve.staged.StageMap), one set per kind of
        suture term (their carry functions compiled once)."""
        def build():
            return tuple(self._on_half(m) for m in (
                StageMap("pressurise", lambda d, c, data: self._materials(d),
                         preop_carry(self.parts, self._nodes, snug=True)),
                StageMap("tighten", self.design_map, tied_lengths(sut)),
                StageMap("suture", self._tied)))
        return self._kept_fn(("maps", term_kind(sut)), build)

    # --- the mirror half: the stages solved on it, their maps and outcomes the whole's --
    def _lifted(self, q) -> np.ndarray:
        """The whole eye's state (n_dof,) of a solved state (numpy)."""
        return q if self.mir is None else self.mir.lift(q)

    def _on_half(self, stage: StageMap) -> StageMap:
        """``stage`` on the solved model: on the mirror half, T's params halved where they
        are the half's (theta_half: the cavity's volumes) and C evaluated on the lifted
        whole state and params (the whole eye's volume, snug fit, optics, suture lengths),
        both JAX, so that the staged adjoint on the half differentiates the whole eye's
        procedure; unchanged for the whole eye."""
        if self.mir is None:
            return stage
        lift, half = self.mir.lift_traced, self.model1

        def params(design, carry, data):
            return theta_half(stage.params(design, carry, data), half)

        def carry(q, theta, data):
            return stage.carry(lift(q), theta_whole(theta, half), data)
        return StageMap(stage.name, params, None if stage.carry is None else carry)

    def outcome_vector(self, res, names, weights=None) -> tuple[Callable, dict]:
        """StagedSimulator.outcome_vector; on the mirror half, the whole eye's outcomes of
        the lifted state (the data: the whole eye's cavity and sutures)."""
        if self.mir is None:
            return super().outcome_vector(res, names, weights)
        names, sut, sol = tuple(names), res.sutures, res.stages[-1].solution
        lift, half = self.mir.lift_traced, self.model1

        def build():
            f = outcome_function(names, self.parts.eye.mesh.nodes, self._nodes, sut)
            return lambda q, theta, carry, data: f(lift(q), theta_whole(theta, half), carry,
                                                   data)
        f = self._kept_fn(("outcomes", names, term_kind(sut)), build)
        return f, outcome_data_of(self._cavity, sut, self.mir.lift(sol.q),
                                  theta_whole(sol.theta, half), weights)

    @staticmethod
    def _with(theta, values) -> dict:
        """theta with the params ``values`` (term -> param -> array) set (numpy)."""
        out = dict(theta)
        for term, ps in values.items():
            out[term] = {**out[term], **{k: np.asarray(v) for k, v in ps.items()}}
        return out

    def _stage1_key(self, design) -> tuple:
        return tuple(float(design[f"c10_{m}"]) for m in self._mat_row) + (float(design["zonule_E"]),)

    def _preop(self, sol1: Solution, materials: tuple) -> Preop:
        _, _, theta2 = close_cavity(self.model, sol1.q, sol1.theta, "cavity", "iop")
        node = snug_node(self.parts, self._lifted(sol1.q))
        pre_map = self.maps(self.model.term("sutures"))[0]
        carry = hand_on(pre_map, sol1.q, self._preop_theta(sol1.theta), self._preop_data(node))
        return Preop(sol1, theta2, node, carry, materials)

    def _preop_theta(self, theta) -> dict:
        """The pre-operative stage's params as its adjoint sees them: stage 1's own."""
        return theta

    def _preop_data(self, node) -> dict:
        """The data of the pre-operative stage's carry (its C)."""
        return {"cavity": (self._cavity.data, self._cavity.dofs), "node": node}

    def _stage1(self, design, start: Result | None = None) -> Preop:
        """The pre-operative eye for the design's material constants: the case's
        (:attr:`preop`) or the start result's where their constants are the design's, else
        continued to the design's constants in one step from the start result's (or the
        case's). Nothing is kept: a run depends on its design and its start alone."""
        want = self._stage1_key(design)
        for pre in ((start.preop,) if start is not None else ()) + (self.preop,):
            if want == pre.materials:
                return pre
        prev = (self.preop if start is None else start.preop).sol1
        target = self._with(prev.theta, stage_params(self.maps(self.model.term("sutures"))[0],
                                                     design, {}))
        ramp = {k: target[k] for k in ("solid", "zonule")}
        s1 = self.stage1
        try:
            sol1 = _lean(solve(self.model1, [Stage(s1.name, 1, s1.prescribed, params=ramp,
                                                   active=s1.active)],
                               q0=prev.q, theta=prev.theta, options=self.options))
        except ConvergenceError as exc:
            log.warning("pre-operative warm start failed (%s); pressurising again",
                        str(exc).splitlines()[0])
            start = self._with(self.model1.theta0(), ramp)
            sol1 = _lean(solve(self.model1, [s1], theta=start, options=self.options))
        return self._preop(sol1, want)

    def _theta2(self, design, sut, pre: Preop, bites: BiteRays):
        """Stage 2's params: T_2 (design_map) on the closed pre-operative eye."""
        th = {**pre.theta2, "sutures": sut.params,
              "buckle": {**pre.theta2["buckle"], "ridge": self.stage2.params["buckle"]["ridge"]}}
        return self._with(th, stage_params(self.maps(sut)[1], design, pre.carry, bites))

    def _model(self, sut):
        """The stage-2 model with the design's suture term (on the mirror half, its half)."""
        if self.mir is not None:
            sut = half_term(sut, self.mir, len(self.mir.partner))
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
        elif self.mir is not None:
            fixed.append("buckle_meridian_deg")
            why["buckle_meridian_deg"] = ("the case is solved on its mirror half (symmetry = "
                                          "'mirror'), and a buckle turned off the plane y = 0 "
                                          "breaks the symmetry; plan the meridian with "
                                          "symmetry = 'none'")
        if not self.params.get("volume_regulation", False):
            fixed += list(TIMELINE_VARIABLES)
            why.update({k: "it belongs to the surgery's timeline; set volume_regulation = "
                        "true in the case (eyefem.eye.timeline)" for k in TIMELINE_VARIABLES})
        for k in fixed:
            if design[k] != d0[k]:
                raise ValueError(f"design variable '{k}' = {design[k]} cannot vary in this "
                                 f"case: {why[k]}")
        for k in TIMELINE_VARIABLES:
            if not design[k] >= 0:
                raise ValueError(f"design variable '{k}' = {design[k]}; must be >= 0")
        for k in MATERIAL_VARIABLES:
            if k in design and not design[k] > 0:
                raise ValueError(f"design variable '{k}' = {design[k]}; a material constant "
                                 "must be > 0")

    # --- forward ------------------------------------------------------------------
    def run(self, design: dict | None = None, *, start: Result | None = None) -> Result:
        """Solve the stages for a design (missing variables: the case's values).

        With ``start`` (a converged result of this simulator, e.g. the nearby design an
        optimiser solved last) its stage-2 and stage-3 states are continued to the design
        in one step each; if that continuation fails within WARM_START_LIMITS, or without
        ``start``, the design is solved along the full load path from the pre-operative
        eye. The equilibria are path independent: both give the same outcomes to the
        Newton tolerance."""
        if start is not None:
            n = np.shape(start.sol2.q) if isinstance(start, Result) else None
            if n != (self.model1.n_dof,):
                raise ValueError(f"start = {type(start).__name__} with states of shape {n}: "
                                 "not a result of this simulator (its states have "
                                 f"{self.model1.n_dof} unknowns); pass what its run() "
                                 "returned, or no start")
            try:
                return self._run(design, start=start)
            except ConvergenceError as exc:
                log.warning("warm start failed (%s); solving the design from the "
                            "pre-operative state", str(exc).splitlines()[0])
        return self._run(design)

    def _prepared(self, design, start: Result | None = None) -> Prepared:
        """What a run of ``design`` (continued from ``start``, if given) starts from
        (:class:`Prepared`)."""
        design = {**self.design0(), **(design or {})}
        self._check(design)
        pre = self._stage1(design, start)
        sut = suture_term(self.parts, self.scale0, design["suture_width"],
                          design["buckle_meridian_deg"])
        model = self._model(sut)
        bites = bite_rays(self.parts, design["suture_width"], design["buckle_meridian_deg"])
        maps = self.maps(sut)
        th2 = self._theta2(design, sut, pre, bites)
        ramped = {k: th2[k] for k in self._ramped}
        start = {**th2, **{k: pre.theta2[k] for k in self._ramped if k not in ("solid", "zonule")}}
        start["cavity"] = {**start["cavity"], "bulk": th2["cavity"]["bulk"]}
        return Prepared(design, pre, sut, model, bites, maps, th2, ramped, start)

    def _warm_options(self) -> NewtonOptions:
        """The Newton options of a warm start: the case's within WARM_START_LIMITS."""
        lim = WARM_START_LIMITS
        o = self.options
        return dataclasses.replace(o, max_iter=min(o.max_iter, lim["max_iter"]),
                                   max_cuts=min(o.max_cuts, lim["max_cuts"]),
                                   stall_cut=lim["stall_cut"])

    def _run(self, design, *, start: Result | None = None):
        prev = start  # the result to continue from, or None: the full load path
        prep = self._prepared(design, start)
        design, pre, sut, model, bites, maps = (prep.design, prep.preop, prep.sutures,
                                                prep.model, prep.bites, prep.maps)
        held, ramped = self.stage2.prescribed, prep.ramped
        if prev is None:
            sol2 = solve(model, [Stage("tighten", self.stage2.n_steps, held, params=ramped,
                                       active=self.stage2.active)],
                         q0=pre.sol1.q, theta=prep.start, options=self.options)
        else:
            theta2 = {**prev.sol2.theta, "sutures": prep.theta2["sutures"]}
            sol2 = solve(model, [Stage("tighten", 1, held, params=ramped, active=self.stage2.active)],
                         q0=prev.sol2.q, theta=theta2, options=self._warm_options())
        sol2 = _lean(sol2)
        sut_data = (sut.data, sut.dofs)
        carry2 = hand_on(maps[1], sol2.q, sol2.theta, sut_data)
        th3 = self._with(sol2.theta, stage_params(maps[2], design, {**pre.carry, **carry2},
                                                  bites))
        same_faces = prev is not None and np.array_equal(prev.sutures.nodes_a, sut.nodes_a)
        if same_faces:  # continuation of every param from the previous design's state
            sol3 = solve(model, [Stage("suture", 1, self.stage3.prescribed,
                                       params={k: th3[k] for k in self._ramped + ("sutures",)},
                                       active=self.stage3.active)],
                         q0=prev.sol3.q, theta=prev.sol3.theta, options=self._warm_options())
        else:
            untied = {**th3, "sutures": {**th3["sutures"], "tightening": 0 * th3["sutures"]["tightening"]}}
            sol3 = solve(model, [Stage("suture", self.stage3.n_steps, self.stage3.prescribed,
                                       params={"sutures": th3["sutures"]},
                                       active=self.stage3.active)],
                         q0=sol2.q, theta=untied, options=self.options)
        sol3 = _lean(sol3)
        its = sum(r.iterations for r in sol2.history + sol3.history)
        stages = (StageRecord(maps[0], pre.sol1, None, self._preop_data(pre.node), pre.carry),
                  StageRecord(maps[1], sol2, bites, sut_data, carry2),
                  StageRecord(maps[2], sol3, bites))
        res = Result(design, {}, stages, sut, bites, its, pre)
        return self._evaluated(res, sol3.q, sol3.theta, {**pre.carry, **carry2})

    # --- gradients (outcomes and the backward sweep: StagedSimulator) -----------------
    def _gradients(self, res: Result, f, data) -> list[dict[str, float]]:
        """Every design variable's gradient (DESIGN_VARIABLES; an encircling buckle's
        meridian: 0; on the mirror half, the meridian's: 0, the outcomes being even in the
        turn off the plane)."""
        totals = super()._gradients(res, f, data)
        if self.parts.buckle.encircling or self.mir is not None:  # no meridian
            for total in totals:
                total["buckle_meridian_deg"] = 0.0
        return [{k: total.get(k, 0.0) for k in DESIGN_VARIABLES} for total in totals]

    def jacobian(self, res: Result, variables, outcomes=None) -> np.ndarray:
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


@dataclasses.dataclass(frozen=True)
class TimelineResult(Result):
    """A converged design on the surgery's timeline: as :class:`Result`, its ``stages`` the
    pre-operative eye's and then one StageRecord per step after the closing (tightening,
    wait, paracentesis, suturing, follow-up), and ``steps``: per step its stage, clock
    (minutes from the closing, at its end) and IOP (mmHg)."""

    steps: tuple = ()
    layout: tuple = ()

    @property
    def sol2(self) -> Solution:
        return self._last_of("tighten")

    @property
    def sol3(self) -> Solution:
        return self.stages[-1].solution

    def _last_of(self, stage: str) -> Solution:
        i = max(i for i, s in enumerate(self.steps) if s[0] == stage)
        return self.stages[1 + i].solution


class TimelineSimulator(SurgerySimulator):
    """A rigid-buckle case on the surgery's timeline (``volume_regulation = true``,
    eyefem.eye.timeline): its outcomes at named times and their adjoint gradients.

    ``SurgerySimulator(params)`` of such a case is one of these. The forward run is the
    timeline's load path (eyefem.eye.timeline.timed_stages, with ``events``: a wait and a
    paracentesis at every design): the tightening ramps T_2's params, the wait holds them,
    the paracentesis removes ``paracentesis_volume`` at one instant, the sutures are tied
    at the state it leaves (C: their lengths) and tightened, and the follow-up holds
    everything; the cavity's volume regulation runs at every step (a backward-Euler step of
    its duration). The timeline is path-dependent (what flowed out and when), so every
    design is solved from the pre-operative eye with the case's steps (no warm start).

    Each step after the closing is one stage of eyefem.solve.staged (one StageRecord): its
    params T(design, carry) are the stage's ramp of T_2 / T_3 at the step's load factor,
    the paracentesis, the step's duration (the wait's: delay x its share: so the time's
    derivative is exact, eyefem.eye.timeline.timed_stages) and the regulation's history
    handed on by the step before; its carry C(q, theta) is that history after the step
    (eyefem.fem.regulation.advanced_history), the IOP, and where needed the tied suture
    lengths or the eye's optics and indentation. The timeline outcomes are JAX functions
    of the carried IOPs, clocks and optics, with the definitions summary.json reports
    (eyefem.eye.timeline.table_outcomes, followup_steps): the peak IOP on the table is the
    largest step's, and its derivative that step's (the max is not differentiable where
    two steps tie); the minutes above the closing pressure are the smooth count. One
    backward sweep (eyefem.solve.staged.staged_gradients) gives every outcome's gradient:
    one factorisation and one block adjoint solve per step, the history chained back.

    The outcomes (:attr:`outcome_names`): OUTCOMES at the run's last step (the last
    follow-up time, as summary.json's), then eyefem.eye.timeline.outcome_names.
    """

    halves = False  # the timeline's regulated cavity and relaxing wall: the whole eye

    def __init__(self, params: dict, materials=None, options: NewtonOptions = NewtonOptions()):
        if params.get("buckle_body", "rigid") != "rigid":
            _refuse_timeline(params)
        super().__init__(params, materials, options)
        carried = [t.name for t in self.model.terms if getattr(t, "history_keys", ())
                   and t.name != "cavity"
                   and not (t.name == "solid" and isinstance(t, ViscoelasticQ1P0))]
        if carried:
            raise ValueError(f"{', '.join(carried)}: the timeline's design gradients hand on "
                             "the history of the cavity and of a relaxing wall (the solid's "
                             "ViscoelasticQ1P0) only; this term's history is not "
                             "differentiated through time: plan the case without it, or run "
                             "it with eyefem run")
        self.outcome_names = tuple(OUTCOMES) + timeline.outcome_names(self.params)

    # --- a relaxing wall: its history handed on as the cavity's is ---------------------
    def _wall(self):
        """The relaxing wall (the solid term, a ViscoelasticQ1P0), or None (an elastic one)."""
        terms = {t.name: t for t in self.model1.terms}
        return terms["solid"] if isinstance(terms.get("solid"), ViscoelasticQ1P0) else None

    def _preop_theta(self, theta) -> dict:
        """Stage 1's params with the wall's history before it (none: h = s_prev = 0, time
        0) and its duration dt (``preop_minutes``; 0: pressurised at once), the one step the
        pre-operative eye's history is the result of: at dt = 0 the steps of the
        pressurising stage telescope to it exactly (h = g S0), and the residual at these
        params is the one the last step solved (A = 0, c = 1; with dt > 0 the stage is one
        step). Its carry "wall" (history_at) is the history the first step starts from,
        a function of q_1 and the materials."""
        wall = self._wall()
        if wall is None:
            return theta
        w = theta["solid"]
        return {**theta, "solid": {**w, "h": np.zeros_like(w["h"]),
                                   "s_prev": np.zeros_like(w["s_prev"]), "time": 0.0,
                                   "dt": float(self.stage1.duration or 0.0)}}

    def _preop_data(self, node) -> dict:
        out = super()._preop_data(node)
        wall = self._wall()
        if wall is not None:
            out["wall"] = (wall.data, wall.dofs)
        return out

    def _preop(self, sol1: Solution, materials: tuple) -> Preop:
        """As SurgerySimulator's; with a relaxing wall, ValueError unless the history its
        carry hands on is the one the load path left (a pressurising stage of several
        timed steps, cut by Newton, is not one step)."""
        pre = super()._preop(sol1, materials)
        if self._wall() is not None:
            w = sol1.theta["solid"]
            for k in ("h", "s_prev", "time"):
                got, ref = np.asarray(pre.carry["wall"][k]), np.asarray(w[k])
                scale = max(float(np.max(np.abs(ref), initial=0.0)), 1e-12)
                if float(np.max(np.abs(got - ref), initial=0.0)) > 1e-9 * scale:
                    raise ValueError("the pre-operative eye's wall history is not one step of "
                                     f"preop_minutes = {self.stage1.duration}: the "
                                     "pressurising stage was cut into several timed steps; "
                                     "its gradients through the relaxing wall are not "
                                     "differentiated (run the case with eyefem run)")
        return pre

    def maps(self, sut) -> tuple[StageMap, StageMap, StageMap]:
        """As SurgerySimulator's; with a relaxing wall the pre-operative stage also hands on
        the wall's history ("wall", eyefem.fem.viscoelastic.history_at) at its params
        (:meth:`_preop_theta`)."""
        base = super().maps(sut)
        if self._wall() is None:
            return base

        def build():
            pre = base[0]

            def carry(q, theta, data):
                return {**pre.carry(q, theta, data),
                        "wall": history_at(q, theta["solid"], *data["wall"])}

            return (StageMap(pre.name, pre.params, carry),) + tuple(base[1:])
        return self._kept_fn(("timeline maps", term_kind(sut)), build)

    def run(self, design: dict | None = None, *, start=None) -> TimelineResult:
        """Solve the timeline for a design (missing variables: the case's values), from the
        pre-operative eye whatever ``start`` (the timeline is path dependent: no warm start)."""
        return self._run(design)

    # --- the forward run -----------------------------------------------------------
    def _run(self, design):
        prep = self._prepared(design)
        design, pre, sut, model, bites, maps = (prep.design, prep.preop, prep.sutures,
                                                prep.model, prep.bites, prep.maps)
        th2, ramped = prep.theta2, prep.ramped
        # the ramped params' start values (constants of the pre-operative eye): the buckle's
        # motion, the drained volume, a band's pull; the other params of T_2 start at T_2's
        first = {t: {k: np.asarray(pre.theta2[t][k]) for k in th2[t]
                     if t != "cavity" or k == "dv"} for t in ("buckle", "cavity", "band_pull")
                 if t in th2 and t in pre.theta2}
        p = {**self.params, **{k: float(design[k]) for k in TIMELINE_VARIABLES}}
        stages = timeline.timed_stages(
            [self.stage1, Stage("tighten", self.stage2.n_steps, self.stage2.prescribed,
                                params=ramped, active=self.stage2.active),
             Stage("suture", self.stage3.n_steps, self.stage3.prescribed,
                   active=self.stage3.active)], p, events=True)[1:]
        rec = Recorder(stages, beta=self.options.beta)
        q, theta, carry2, tie = pre.sol1.q, prep.start, {}, None
        sut_data = (sut.data, sut.dofs)
        for st in stages:
            if st.name == "suture":  # tie the sutures at the state the paracentesis left
                tie = len(rec.steps) - 1
                carry2 = hand_on(maps[1], q, theta, sut_data)
                th3 = self._with(theta, stage_params(maps[2], design, {**pre.carry, **carry2},
                                                     bites))
                theta = {**th3, "sutures": {**th3["sutures"],
                                            "tightening": 0 * th3["sutures"]["tightening"]}}
                st = dataclasses.replace(st, params={"sutures": th3["sutures"]})
            sol = solve(model, [st], q0=q, theta=theta, options=self.options, on_step=rec)
            q, theta = sol.q, sol.theta
        its = sum(r.iterations for r in rec.records)
        records, steps, layout = self._records(rec, stages, model, sut, bites, pre, first, p,
                                               tie)
        sol1 = dataclasses.replace(pre.sol1, theta=self._preop_theta(pre.sol1.theta))
        pre_rec = StageRecord(maps[0], sol1, None, self._preop_data(pre.node), pre.carry)
        res = TimelineResult(design, {}, (pre_rec,) + records, sut, bites, its, pre, steps,
                             layout)
        return self._evaluated(res, q, records[-1].solution.theta,
                               _carries((pre_rec,) + records[:-1]))

    def _records(self, rec: Recorder, stages, model, sut, bites, pre, first, p, tie):
        """One StageRecord per recorded step, the steps' (stage, clock, IOP) and the layout
        (which steps are on the table, which at each follow-up time, which is last)."""
        by_name = {s.name: s for s in stages}
        cav = model.term("cavity")
        clock = [float(th["cavity"]["time"]) + float(th["cavity"]["dt"])
                 for *_, th in rec.steps]
        table = tuple(i for i, s in enumerate(rec.steps) if s[0] != "follow-up")
        follow = [i for i, s in enumerate(rec.steps) if s[0] == "follow-up"]
        end = clock[table[-1]]
        hits = timeline.followup_steps([clock[i] - end for i in follow], p)
        minutes = dict(timeline.parse_followup(p["followup"]))
        at = tuple((name, follow[j], timeline.shape_at_week(minutes[name]))
                   for name, j in hits.items())
        shape = {i for _, i, s in at if s}
        last = len(rec.steps) - 1
        kinds = tuple("tie" if i == tie else "shape" if i in shape else "plain"
                      for i in range(len(rec.steps)))
        asms, out, steps = {}, [], []
        wall = self._wall() is not None
        for i, (name, t, model_i, q_i, th_i) in enumerate(rec.steps):
            stage = by_name[name]
            if name not in asms:
                mask = np.zeros(model_i.n_dof, bool)
                mask[stage.prescribed[0]] = True
                asms[name] = Assembler(model_i, mask, beta=self.options.beta)
            t0 = rec.steps[i - 1][1] if i and rec.steps[i - 1][0] == name else 0.0
            data = {"stage": name, "t": float(t), "t0": float(t0), "bites": bites,
                    "minutes": float(stage.duration or 0.0), "start": first,
                    "history": f"history/{i - 1}" if i else None,
                    "wall": (f"wall/{i - 1}" if i else "wall") if wall else None,
                    "h0": None if i else {k: np.asarray(th_i["cavity"][k]) for k in HISTORY_KEYS}}
            smap = self._step_map(kinds[i], sut)
            cdata = self._carry_data(kinds[i], model_i)
            values = compiled(smap.carry)(
                jnp.asarray(q_i), jax.tree_util.tree_map(jnp.asarray, th_i), cdata)
            names = {k: k if k == "L0" else f"{k}/{i}" for k in values}
            carry = {names[k]: jax.tree_util.tree_map(np.asarray, v) for k, v in values.items()}
            sol = Solution(model_i, q_i, th_i, [rec.records[i]], asms[name], None, stage.active)
            out.append(StageRecord(smap, sol, data, cdata, carry, names))
            steps.append((name, clock[i], float(values["iop"])))
        layout = (table, at, last, kinds)
        return tuple(out), tuple(steps), layout

    # --- each step as a stage: its params and what it hands on ------------------------
    def _step_params(self, design, carry, data) -> dict:
        """T of one step (JAX): the stage's params at the step's load factor t, the
        paracentesis, the step's duration dt and the history the step starts from. The
        forward run's are the load path's own (eyefem.solve.loadpath: the stage's ramp
        (1 - t) a + t b at the load factors Newton's step cutting chose, the history moved
        on by each term's advance), built before t is known; :meth:`params_mismatch`
        checks that the two agree to roundoff."""
        stage, t, bites = data["stage"], data["t"], data["bites"]
        if stage in ("suture", "follow-up"):
            out = self._tied(design, carry, bites)
        else:
            out = self.design_map(design, carry, bites)
        out = {term: dict(ps) for term, ps in out.items()}
        if stage == "tighten":  # the ramp from the pre-operative eye's values
            for term, ps in data["start"].items():
                for k, s0 in ps.items():
                    if k in out.get(term, {}):
                        out[term][k] = (1.0 - t) * jnp.asarray(s0) + t * out[term][k]
        elif stage == "suture":  # tied at 0, tightened along the stage
            out["sutures"]["tightening"] = t * out["sutures"]["tightening"]
        vp = design["paracentesis_volume"]
        removed = {"tighten": 0.0 * vp, "wait": 0.0 * vp, "paracentesis": t * vp}.get(stage, vp)
        minutes = design["paracentesis_delay_minutes"] if stage == "wait" else data["minutes"]
        h = carry[data["history"]] if data["history"] is not None else data["h0"]
        full = self._full
        out["cavity"] = {**out["cavity"], "paracentesis": full("cavity", "paracentesis", removed),
                         "dt": full("cavity", "dt", (t - data["t0"]) * minutes),
                         **{k: full("cavity", k, h[k]) for k in HISTORY_KEYS}}
        if data.get("wall") is not None:  # the relaxing wall's history, handed on as h is
            w = carry[data["wall"]]
            out["solid"] = {**out["solid"], "dt": full("solid", "dt", (t - data["t0"]) * minutes),
                            **{k: full("solid", k, w[k]) for k in ViscoelasticQ1P0.history_keys}}
        return out

    def _step_map(self, kind: str, sut) -> StageMap:
        """The StageMap of a step of ``kind`` ("plain", "tie": also the tied suture lengths
        L0, "shape": also the optics and the indentation), one per kind and suture term
        (its carry compiled once)."""
        def build():
            X, nodes, tie_rule = self.parts.eye.mesh.nodes, self._nodes, tied_lengths(sut)

            def carry(q, theta, data):
                P = cavity_pressure(q, theta["cavity"], *data["cavity"])  # the IOP, MPa
                h = advanced_history(P, theta["cavity"])
                out = {"history": {k: h[k] for k in HISTORY_KEYS}, "iop": P / MMHG}
                if kind == "tie":
                    out.update(tie_rule(q, theta, data["sutures"]))
                if kind == "shape":
                    out["optics"] = eye_optics(X, q, nodes)
                    out["indentation"] = indentation(X, q, nodes)
                if "wall" in data:  # a relaxing wall's history after the step
                    out["wall"] = history_at(q, theta["solid"], *data["wall"])
                return out

            return StageMap(f"step ({kind})", self._step_params, carry)
        return self._kept_fn(("step_map", kind, term_kind(sut)), build)

    @staticmethod
    def _carry_data(kind: str, model) -> dict:
        cav = model.term("cavity")
        out = {"cavity": (cav.data, cav.dofs)}
        if kind == "tie":
            sut = model.term("sutures")
            out["sutures"] = (sut.data, sut.dofs)
        wall = {t.name: t for t in model.terms}.get("solid")
        if isinstance(wall, ViscoelasticQ1P0):
            out["wall"] = (wall.data, wall.dofs)
        return out

    # --- outcomes ---------------------------------------------------------------------
    def outcome_vector(self, res: TimelineResult, names, weights=None) -> tuple[Callable, dict]:
        """(f, data) as :meth:`SurgerySimulator.outcome_vector`, for the names of
        :attr:`outcome_names`: f(q, theta, carry, data) at the last step, the timeline
        outcomes read from the carries of the steps (the last step's from q, theta). One
        f per outcome list, suture term kind and layout of the steps."""
        names, sut = tuple(names), res.sutures
        unknown = [n for n in names if n not in self.outcome_names]
        if unknown:
            raise KeyError(f"unknown outcomes {unknown}; known: {list(self.outcome_names)}")
        table, at, last, kinds = res.layout
        p = self.params

        def build():
            std = tuple(n for n in names if n in OUTCOMES)
            f_std = outcome_function(std, self.parts.eye.mesh.nodes, self._nodes, sut)
            own = self._step_map(kinds[last], sut).carry

            def f(q, theta, carry, data):
                mine = own(q, theta, {"cavity": data["cavity"]})

                def get(key, i):
                    return mine[key] if i == last else carry[f"{key}/{i}"]

                vals = dict(zip(std, f_std(q, theta, carry, {**data, "weights": None}))) \
                    if std else {}
                t = jnp.stack([jnp.zeros(())] + [get("history", i)["time"] for i in table])
                iop = jnp.stack([jnp.asarray(p["iop_mmhg"], jnp.float64)]
                                + [get("iop", i) for i in table])
                vals.update(timeline.table_outcomes(t, iop, p))
                for name, i, shape in at:
                    vals[f"iop_{name}_mmhg"] = get("iop", i)
                    if shape:
                        ch = {**changes(get("optics", i), carry["optics"]),
                              "indentation_mm": get("indentation", i)}
                        vals.update({timeline.shape_name(k, name): ch[k]
                                     for k in timeline.SHAPE_OUTCOMES})
                values = jnp.stack([vals[n] for n in names])
                w = data["weights"]
                return values if w is None else jnp.reshape(jnp.dot(w, values), (1,))
            return f

        f = self._kept_fn(("timeline outcomes", names, term_kind(sut), res.layout), build)
        sol = res.stages[-1].solution
        return f, outcome_data(sol.model, sol.q, sol.theta, weights)

    def params_mismatch(self, res: TimelineResult) -> float:
        """The largest difference, relative to the param's size, between each step's
        params as T gives them (JAX, what the adjoint differentiates) and those the load
        path solved with: roundoff where the two agree (a check of the step maps)."""
        return params_mismatch(res.stages, res.design, lambda r: isinstance(
            r.params_data, dict) and "stage" in r.params_data)  # the timeline's steps


def _carries(records) -> dict:
    """The carries the records handed on, by name (a later one's over an earlier one's)."""
    out: dict = {}
    for r in records:
        out.update(r.carry)
    return jax.tree_util.tree_map(jnp.asarray, out)


def states_only(res):
    """A result (:class:`Result`, :class:`RingResult`, :class:`TimelineResult`) keeping its
    stages' states, not their assemblers (the tangent's sparsity and scatter maps: about
    50 MB a stage on ``fine``): what the next design starts from (``run(design,
    start=...)``), when its own gradients are taken already. Its gradients cannot be taken
    (Solution.factorised says so); the pre-operative stage's solution is the simulator's
    and keeps its assembler."""
    stages = tuple(rec if i == 0 else dataclasses.replace(
        rec, solution=dataclasses.replace(rec.solution, assembler=None))
        for i, rec in enumerate(res.stages))
    return dataclasses.replace(res, stages=stages)


def _lean(sol: Solution) -> Solution:
    """``sol`` without its last factorisation (freed once nothing else holds it): a
    design's gradients factorise each stage's tangent again at its converged state
    (eyefem.solve.records.Solution.factorised, one factorisation a stage, in the backward
    sweep), so that a simulator and the results a caller holds keep states, not
    factorisations (on ``fine``, kept: 0.6 GB more a simulation, docs/performance.md)."""
    return dataclasses.replace(sol, solver=None)


@dataclasses.dataclass(frozen=True)
class RingResult:
    """A converged design of a deformable ring: outcome values, its stages
    (eyefem.solve.staged.StageRecord: pressurise, tighten, suture) and its suture term."""

    design: dict
    outcomes: dict
    stages: tuple
    sutures: object
    newton_iterations: int


class RingSimulator(StagedSimulator):
    """Simulate a deformable band or tire case (buckle_body = 'deformable', encircling)
    for many designs, with adjoint gradients, through the stages its body declares
    (eyefem.eye.bodies.DeformableRing.design_params, the same as ``eyefem run``'s).

    The design variables are those the ring's stages take as params
    (DeformableRing.VARIABLES: tightening of a closed loop, suture tightening, drained
    volume, liquid bulk modulus, suture EA); they leave the pressurised eye (stage 1) and
    the band's snug fit on it unchanged, so stage 1 is solved once. Each design solves
    stages 2 and 3 from it, with the case's load steps (no warm start); the gradient is
    one backward sweep over the three stages (eyefem.solve.staged.staged_gradients).

    Args: as :class:`SurgerySimulator`.
    """

    def __init__(self, params: dict, materials=None, options: NewtonOptions = NewtonOptions()):
        self.params = whole_eye(params)
        self.options = options
        _refuse_timeline(self.params)
        setup = surgery(self.params, materials)
        self.parts = setup.parts
        if self.params.get("buckle_body") != "deformable" or not self.parts.buckle.encircling:
            raise ValueError("RingSimulator: a deformable band or tire (buckle_body = "
                             "'deformable', buckle = 'band', 'tire_flat' or 'tire_ridged')")
        self.body = DeformableRing()
        self.variables = tuple(v for v in self.body.VARIABLES
                               if v != "tightening" or self.parts.band.closed)
        self.stage1, self.stage2, self.stage3 = setup.stages
        self.model1 = setup.model
        self._nodes = outcome_nodes(self.parts)
        self._compiled: dict = {}
        cav = self.model1.term("cavity")
        self._cavity = (cav.data, cav.dofs)
        self.sol1 = _lean(solve(self.model1, [self.stage1], options=options))
        self.carry1 = hand_on(self._maps()[0], self.sol1.q, self.sol1.theta,
                              {"cavity": self._cavity})

    def design0(self) -> dict:
        return {k: float(self.params[k]) for k in self.variables}

    def _maps(self) -> tuple[StageMap, StageMap, StageMap]:
        """The three stages as data: T_2 / T_3 the ring's design params
        (DeformableRing.design_params) with the closed volume and the tied lengths."""
        parts = self.parts

        def tighten(design, carry, data):  # T_2
            t2, _ = self.body.design_params(parts, design)
            return {**t2, "cavity": {**t2["cavity"], "v_ini": carry["volume"]}}

        def suture(design, carry, data):  # T_3
            _, t3 = self.body.design_params(parts, design)
            return {**tighten(design, carry, data),
                    "sutures": tied(t3["sutures"], carry["L0"])}

        # the suture term's methods only (term_kind): the one the band is refitted with
        # in stage 2 is of the same kind
        return self._kept_fn("maps", lambda: (
            StageMap("pressurise", lambda d, c, data: {},
                     preop_carry(parts, self._nodes, snug=False)),
            StageMap("tighten", tighten, tied_lengths(self.model1.term("sutures"))),
            StageMap("suture", suture)))

    def _check(self, design: dict) -> None:
        for k in design:
            if k not in self.variables:
                raise ValueError(f"design variable '{k}' cannot vary for a deformable "
                                 f"{self.parts.buckle.kind}: its design variables are "
                                 f"{list(self.variables)}")

    def run(self, design: dict | None = None, *, start=None) -> RingResult:
        """Solve stages 2 and 3 for a design (missing variables: the case's values), from
        the pre-operative eye whatever ``start`` (the ring has no warm start)."""
        self._check(design or {})
        design = {**self.design0(), **(design or {})}
        maps = self._maps()

        def stage(s, values):
            params = {t: {**s.params.get(t, {}), **ps} for t, ps in values.items()}
            return dataclasses.replace(s, params={**s.params, **params})

        t2 = stage_params(maps[1], design, self.carry1)
        sol2 = _lean(solve(self.model1, [stage(self.stage2, t2)], q0=self.sol1.q,
                           theta=self.sol1.theta, options=self.options))
        sut = sol2.model.term("sutures")
        carry2 = hand_on(maps[1], sol2.q, sol2.theta, (sut.data, sut.dofs))
        t3 = stage_params(maps[2], design, {**self.carry1, **carry2})
        sol3 = _lean(solve(sol2.model, [stage(self.stage3, t3)], q0=sol2.q, theta=sol2.theta,
                           options=self.options))
        stages = (StageRecord(maps[0], self.sol1, None, {"cavity": self._cavity}, self.carry1),
                  StageRecord(maps[1], sol2, None, (sut.data, sut.dofs), carry2),
                  StageRecord(maps[2], sol3))
        its = sum(r.iterations for r in sol2.history + sol3.history)
        res = RingResult(design, {}, stages, sut, its)
        return self._evaluated(res, sol3.q, sol3.theta, {**self.carry1, **carry2})


def whole_eye(params: dict) -> dict:
    """The case's parameters for a design simulator that solves the whole eye (the
    timeline's and the deformable ring's): a mirror-half case (``symmetry = 'mirror'``) is
    simulated whole (the half gives the whole's outcomes to 2e-9, docs/case_files.md "The
    mirror half")."""
    if params.get("symmetry", "none") == "none":
        return dict(params)
    log.info("symmetry = '%s': this design simulator solves the whole eye",
             params["symmetry"])
    return {**params, "symmetry": "none"}


def _refuse_timeline(params: dict):
    """ValueError for a deformable ring on the surgery's timeline: RingSimulator solves the
    closed cavity's three stages (the timeline's gradients are the rigid buckle's,
    TimelineSimulator)."""
    if params.get("volume_regulation", False):
        raise ValueError("volume_regulation = true with a deformable band or tire: the design "
                         "gradients follow the surgery's timeline for the rigid buckle only "
                         "(TimelineSimulator); set buckle_body = 'rigid', or run the "
                         "deformable ring's timeline with eyefem run")

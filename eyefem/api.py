"""The JAX-native entry point: ``simulate(case, design) -> outcomes``, differentiable in the design.

``simulate`` runs a surgery case with a rigid buckle or a deformable band or tire (stages:
pressurise, fit and tighten the buckle, tie the sutures) and returns its outcomes
(eyefem.eye.variables.OUTCOMES)::

    import jax, eyefem
    jax.config.update("jax_enable_x64", True)
    iop = lambda d: eyefem.simulate("cases/surgery/case1.toml", d, mesh="coarse")["iop_mmhg"]
    jax.grad(iop)({"suture_width": 9.0})      # d IOP / d suture width, mmHg/mm

Under ``jax.grad`` / ``jax.vjp`` / ``jax.jacrev`` / ``jax.jit`` the forward solve is a
``jax.pure_callback`` (Newton on the host, scipy sparse), wrapped in a ``jax.custom_vjp``
whose backward pass is the adjoint: a host callback takes the cotangent of the outcomes
and returns the gradient of their weighted sum (SurgerySimulator.weighted_gradient: one
backward sweep over the stages, eyefem.solve.staged, three adjoint solves on the stages'
last factorisations, whatever the cotangent), so
``jax.grad`` of any scalar of the outcomes costs one forward solve and three adjoint
solves; ``jax.jacrev`` one backward pass per outcome. Forward-mode (``jax.jvp``,
``jax.jacfwd``) is not supported (custom_vjp). On the surgery's timeline the backward pass
is one adjoint per load step (eyefem.eye.simulators.TimelineSimulator). A call without
traced values runs the host solve directly and returns floats.

A :class:`Simulation` is one case on one mesh level, ready for designs: its simulator
(the pressurised eye solved, the kernels compiled) and the converged states of its recent
designs (each new design starts from the last). Hold one to decide what is kept and for
how long::

    sim = eyefem.Simulation("cases/surgery/case1.toml", mesh="coarse")
    sim({"suture_width": 9.0})["iop_mmhg"]
    jax.grad(lambda d: sim(d)["iop_mmhg"])({"suture_width": 9.0})

``simulate(path_or_case, ...)`` is the one-line form: it keeps the CACHED_SIMULATORS
Simulations it used last, keyed by the parsed case's contents (a case-file path and the
Case read from it share one); ``simulate(sim, design)`` runs a Simulation you hold.
"""

from __future__ import annotations

import collections
import dataclasses
import difflib
import hashlib
import logging
import threading
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.catalog import schemas, solver_defaults
from eyefem.eye.simulators import RingSimulator, SurgerySimulator
from eyefem.eye.variables import DESIGN_VARIABLES, OUTCOMES
from eyefem.io import casefile
from eyefem.io.casefile import Case

log = logging.getLogger(__name__)

CACHED_SIMULATORS = 4
"""How many (case, mesh) Simulations simulate() keeps for the cases given by path or Case
(least recently used dropped); a Simulation you hold is yours."""
REMEMBERED_DESIGNS = 8
"""How many converged designs each simulator remembers (their states, and the gradients of
single outcomes computed there)."""

_recent: collections.OrderedDict = collections.OrderedDict()  # key -> Simulation
_recent_lock = threading.Lock()


def load_case(path: str | Path) -> Case:
    """Read and validate a case file against the schemas of every known problem."""
    return casefile.load_case(path, schemas(), solver_defaults())


def with_material_preset(case: Case, preset: str) -> Case:
    """The case with the material preset ``preset`` (eyefem.eye.presets.PRESETS): its
    materials_preset set and its own tables of the preset's tissues dropped (a warning
    names them)."""
    from eyefem.eye.presets import tissues_replaced

    kept, dropped = tissues_replaced(case.materials, preset)
    if dropped:
        log.warning("--materials %s replaces the case file's [materials] tables of %s",
                    preset, ", ".join(dropped))
    return dataclasses.replace(case, parameters={**case.parameters, "materials_preset": preset},
                               materials=kept)


def clear_cache() -> None:
    """Forget the Simulations simulate() has kept for cases given by path or Case (those
    you hold are untouched)."""
    with _recent_lock:
        _recent.clear()


def simulate(case: str | Path | Case | Simulation, design: dict | None = None, *,
             mesh: str | None = None) -> dict:
    """Outcomes of a surgery case at a design; differentiable in the design.

    Args:
      case: a case-file path (relative to the current directory), a parsed Case
        (load_case) or a :class:`Simulation`; the case's ``[case] problem`` must be
        "surgery", with a rigid buckle (SurgerySimulator) or a deformable band or tire
        (RingSimulator: the design variables its stages take as params,
        RingSimulator.variables). A path or Case runs on the Simulation simulate() keeps
        for it (CACHED_SIMULATORS), built on first use.
      design: design-variable name -> value (eyefem.eye.variables.DESIGN_VARIABLES: mm,
        degrees, N, MPa, mm^3 as documented there), overriding the case; scalars, Python
        floats or JAX values (traced under jax.grad / jax.jit).
      mesh: eye mesh level overriding the case's ``[parameters] mesh`` ("coarse", ...);
        with a Simulation, None or its own level.

    Returns:
      outcome name (OUTCOMES: iop_mmhg, indentation_mm, axial_length_change_mm,
      max_suture_force_N, refraction_change_D, corneal_power_change_D,
      corneal_astigmatism_D, anterior_chamber_depth_change_mm) -> float, or 0-d float64
      array when the design is traced. A case on the surgery's timeline
      (``volume_regulation = true``: eyefem.eye.simulators.TimelineSimulator) reports these at
      its last follow-up time and then its timeline outcomes (peak_iop_on_table_mmhg,
      minutes_above_cra_closing, iop_end_of_surgery_mmhg, iop_48h_mmhg, ...,
      refraction_change_1w_D, ...: eyefem.eye.timeline.outcome_names), all
      differentiable; its design may also set paracentesis_volume (uL) and
      paracentesis_delay_minutes.

    Raises ValueError for a case simulate cannot run, an unknown design variable or mesh
    level, or a variable the case cannot vary; RuntimeError when x64 is off (call
    ``jax.config.update("jax_enable_x64", True)`` first: switching it inside a traced
    function would not change the types already traced).
    """
    _check_x64()
    _check_design(dict(design or {}))  # before a simulator is built for a misspelt name
    if isinstance(case, Simulation):
        if mesh is not None and mesh != case.mesh:
            raise ValueError(f"simulate: mesh = {mesh!r} for a Simulation on the {case.mesh!r} "
                             "mesh; build eyefem.Simulation(case, mesh=...) for another level")
        return case(design)
    return _kept(case, mesh)(design)


def _check_x64() -> None:
    if not jax.config.jax_enable_x64:
        raise RuntimeError("eyefem.simulate needs 64-bit floats: call "
                           "jax.config.update('jax_enable_x64', True) before any JAX work "
                           "(the Newton solve and its adjoint lose accuracy in float32)")


def _check_design(design: dict) -> None:
    for k, v in design.items():
        if k not in DESIGN_VARIABLES:
            m = difflib.get_close_matches(str(k), list(DESIGN_VARIABLES), n=1)
            hint = f" (did you mean '{m[0]}'?)" if m else ""
            raise ValueError(f"unknown design variable '{k}'{hint}; known: "
                             f"{', '.join(DESIGN_VARIABLES)}")
        if np.ndim(v) != 0:
            raise ValueError(f"design variable '{k}' has shape {np.shape(v)}; give one "
                             "scalar per variable")


def _parsed(case) -> Case:
    if isinstance(case, Case):
        return case
    if isinstance(case, (str, Path)):
        return load_case(case)
    raise TypeError(f"simulate: case is a {type(case).__name__}; give a case-file path "
                    "(str or pathlib.Path) or a Case from eyefem.load_case")


def _kept(case, mesh: str | None) -> Simulation:
    """The Simulation simulate() keeps for (case, mesh), built on first use. The key is the
    parsed case's contents (its path resolved), so a path and the Case read from it share
    one."""
    parsed = _parsed(case)
    contents = repr(dataclasses.replace(parsed, path=Path(parsed.path).resolve()))
    key = (hashlib.sha256(contents.encode()).hexdigest(), mesh)
    with _recent_lock:
        if key in _recent:
            _recent.move_to_end(key)
            return _recent[key]
    sim = Simulation(parsed, mesh=mesh)
    with _recent_lock:
        _recent[key] = sim
        while len(_recent) > CACHED_SIMULATORS:
            _recent.popitem(last=False)
    return sim


def _surgery_parameters(case: Case, mesh: str | None) -> dict:
    """The case's surgery parameters with the mesh override; ValueError for a case that
    simulate cannot run."""
    if case.problem != "surgery":
        raise ValueError(f"{case.path}: [case] problem = '{case.problem}'; eyefem.simulate runs "
                         "the rigid-buckle surgery cases (problem = \"surgery\"); run this case "
                         f"with `eyefem run {case.path}` or build it with eyefem.solve")
    params = dict(case.parameters)
    body = params.get("buckle_body", "rigid")
    if body != "rigid" and params.get("buckle") == "sponge_radial":
        raise ValueError(f"{case.path}: [parameters] buckle_body = '{body}' with a sponge; "
                         "eyefem.simulate and its gradients support the rigid buckles and the "
                         "deformable band and tires; set buckle_body = 'rigid', or run the "
                         f"deformable sponge with `eyefem run {case.path}`")
    if mesh is not None:
        field = next(f for f in schemas()["surgery"] if f.name == "mesh")
        if not field.check(mesh):
            raise ValueError(f"simulate: mesh = {mesh!r}; {field.doc}")
        params["mesh"] = mesh
    return params


class Simulation:
    """One surgery case on one mesh level, ready to simulate designs; calling it gives the
    outcomes of a design (as :func:`simulate`), differentiable in the design.

    Building it reads the case, builds its simulator (SurgerySimulator for a rigid buckle,
    RingSimulator for a deformable band or tire; on the mirror half where the case says
    so), which solves the pressurised pre-operative eye; the first call solves its design
    along the case's load path (together tens of seconds on the coarse mesh). Each later
    design is a continuation of the design solved last; the converged states of the last
    ``remembered`` designs are kept, so a repeated or jitted design is not solved again.
    Its case, mesh level and outcome names do not change; :meth:`forget` drops the
    remembered designs.

    Args:
      case: a case-file path or a parsed Case (load_case), ``problem = "surgery"``.
      mesh: eye mesh level overriding the case's ``[parameters] mesh``.
      remembered: how many converged designs to keep (>= 1).

    Raises ValueError for a case simulate cannot run or an unknown mesh level.
    """

    def __init__(self, case: str | Path | Case, *, mesh: str | None = None,
                 remembered: int = REMEMBERED_DESIGNS):
        if int(remembered) < 1:
            raise ValueError(f"Simulation: remembered = {remembered}; keep at least 1 design "
                             "(the warm start of the next)")
        parsed = _parsed(case)
        params = _surgery_parameters(parsed, mesh)
        log.info("simulate: building the simulator of %s on the %s mesh", parsed.path,
                 params["mesh"])
        simulator = (SurgerySimulator if params.get("buckle_body", "rigid") == "rigid"
                     else RingSimulator)
        self._case, self._mesh, self._remembered = parsed, str(params["mesh"]), int(remembered)
        self.sim = simulator(params, parsed.materials, parsed.solver)
        self.names = tuple(getattr(self.sim, "outcome_names", OUTCOMES))  # outcomes, in order
        self.lock = threading.RLock()
        self.memo: collections.OrderedDict = collections.OrderedDict()
        self.functions: dict = {}

    @property
    def case(self) -> Case:
        """The parsed case."""
        return self._case

    @property
    def mesh(self) -> str:
        """The eye mesh level it runs on."""
        return self._mesh

    def __repr__(self) -> str:
        return (f"Simulation({str(self._case.path)!r}, mesh={self._mesh!r}: "
                f"{len(self.memo)} of {self._remembered} designs remembered)")

    def __call__(self, design: dict | None = None) -> dict:
        """Outcomes of ``design`` (name -> value, missing: the case's): floats, or 0-d
        arrays when the design is traced (jax.grad, jax.jacrev, jax.jit)."""
        _check_x64()
        design = dict(design or {})
        _check_design(design)
        if not any(isinstance(v, jax.core.Tracer) for v in design.values()):
            values = self.outcomes({k: float(v) for k, v in design.items()})
            return {k: float(v) for k, v in zip(self.names, values)}
        names = tuple(design)
        x = jnp.stack([jnp.asarray(design[k], dtype=jnp.float64) for k in names])
        y = self.differentiable(names)(x)
        return {k: y[i] for i, k in enumerate(self.names)}

    def forget(self) -> None:
        """Drop the remembered designs (the next design is solved along the full load path
        from the pre-operative eye)."""
        with self.lock:
            self.memo.clear()

    def _entry(self, design: dict) -> dict:
        full = {**self.sim.design0(), **design}
        key = tuple(sorted((k, float(v)) for k, v in full.items()))
        with self.lock:
            if key not in self.memo:  # warm started from the design used last
                last = next(reversed(self.memo.values()))["result"] if self.memo else None
                self.memo[key] = {"result": self.sim.run(design, start=last)}
                while len(self.memo) > self._remembered:
                    self.memo.popitem(last=False)
            self.memo.move_to_end(key)
            return self.memo[key]

    def outcomes(self, design: dict) -> np.ndarray:
        """Outcome values (n_outcomes,) in the order of self.names."""
        res = self._entry(design)["result"]
        return np.array([res.outcomes[k] for k in self.names], dtype=np.float64)

    def cotangent_gradient(self, design: dict, cotangent) -> np.ndarray:
        """d (cotangent . outcomes) / d design (len(design),): three adjoint solves. The
        gradient of a single outcome (a one-hot cotangent: jax.grad of one outcome, a row of
        jax.jacrev) is remembered with the design, so a jitted or repeated call reuses it."""
        entry = self._entry(design)
        weights = {k: float(w) for k, w in zip(self.names, np.asarray(cotangent, np.float64)) if w}
        with self.lock:
            if len(weights) == 1:
                (name, w), = weights.items()
                cache = entry.setdefault("gradients", {})
                if name not in cache:
                    cache[name] = self.sim.gradients(entry["result"], [name])[name]
                grad = {k: w * v for k, v in cache[name].items()}
            else:
                grad = self.sim.weighted_gradient(entry["result"], weights)
        return np.array([grad[k] for k in design], dtype=np.float64)

    def differentiable(self, names: tuple):
        """x (len(names),) -> outcomes (n_outcomes,): a custom_vjp over host callbacks."""
        if names in self.functions:
            return self.functions[names]
        out = jax.ShapeDtypeStruct((len(self.names),), jnp.float64)

        def design_of(x):
            return dict(zip(names, (float(v) for v in np.asarray(x, dtype=np.float64))))

        @jax.custom_vjp
        def outcomes(x):
            return jax.pure_callback(lambda x: self.outcomes(design_of(x)), out, x,
                                     vmap_method="sequential")

        grad = jax.ShapeDtypeStruct((len(names),), jnp.float64)

        def forward(x):
            return outcomes(x), x

        def backward(x, cotangent):
            return (jax.pure_callback(
                lambda x, c: self.cotangent_gradient(design_of(x), c), grad, x, cotangent,
                vmap_method="sequential"),)

        outcomes.defvjp(forward, backward)
        self.functions[names] = outcomes
        return outcomes

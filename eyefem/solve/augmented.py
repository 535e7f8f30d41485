"""The augmented Lagrangian on the Q1P0 volume constraint: one symmetric positive definite
solve per Newton iteration (NewtonOptions.incompressibility = "augmented_lagrangian").

The Q1P0 element (eyefem.fem.solid.SolidQ1P0) holds its volume exactly through one
multiplier lambda_e per element, and the Newton system is a saddle point (a factorisation
of K + B D B^T and a Schur-complement CG on the multipliers around it,
eyefem.solve.linsolve). Here each element's multiplier becomes a fixed estimate
lambda_e^k plus a penalty on the element's volume change

    Pi_e(u) = integral_Ve [W(I1bar, I2bar) + 2 lambda_e^k (J - 1)] dV + kappa_e / (2 V_e) g_e^2
    g_e(u) = integral_Ve (J - 1) dV       [mm^3],   V_e = integral_Ve dV,   kappa_e [MPa]

(N mm), a function of the displacements alone: its gradient is the Q1P0 element's at the
multiplier lambda_eff = lambda_e^k + kappa_e g_e / (2 V_e), its Hessian the Q1P0
displacement block at lambda_eff plus kappa_e / (4 V_e) k_ul k_ul^T (k_ul = dc/du, c = 2 g_e
the constraint of the Q1P0 energy). The Newton matrix is K + B D B^T on the displacements
only, positive definite where the material and the other terms are stable: one Cholesky
factorisation (Pardiso mtype 2, linsolve.SPD) and one back-solve per iteration. Where it
is not (a follower pressure's or a contact's tangent, a pressure the penalty does not
outweigh), the failed Cholesky hands the step to the modified Newton shift, or the matrix
to the symmetric indefinite factorisation (linsolve.factorize). When a load step has
converged, the estimates are updated (Uzawa, FEBio's augmentation: ``laugon``)

    lambda_e^{k+1} = lambda_e^k + kappa_e g_e / (2 V_e)

and the step is iterated again (from the tangent predictor on its last factorisation)
until max_e |g_e| / V_e <= NewtonOptions.uzawa_tol; the estimates carry over to the next
step. At that point the state is the Q1P0 one to the tolerance: the displacements balance
the Q1P0 forces at lambda_eff exactly, and the volume constraint is left at uzawa_tol
(the exact solver: NewtonOptions.vtol on the norm of the constraints).

kappa_e = NewtonOptions.penalty_factor x the element's initial shear modulus
2 (c10 + c01), 100 by default (FEBio's ``laugon``/``atol`` augmentations of its
uncoupled materials are the same scheme, their penalty the material's bulk modulus).
Measured on case 1's pressurisation on the coarse eye (benchmarks/bench_incompressibility.py):
at 10 x mu the first solve left max |Jbar - 1| = 0.1 and the Uzawa updates contracted it
only 2- to 5-fold each (6e-4 after 6); at 1000 x mu Newton did not converge in 40
iterations (the penalty's forces, cubic in the displacements, defeat the line search);
at 100 x mu it reached 1e-6 in 6 updates of 1-2 iterations each. On the inflated shell
10 x mu needs one update a step.

:func:`solve_augmented` is the load path with the transformation (eyefem.solve.loadpath
calls it for that option): the model's SolidQ1P0 terms become :class:`AugmentedQ1P0`
terms (a new Model; nothing is mutated), their multiplier dofs are held at 0 in every
stage, and the callbacks and the returned Solution see the exact model at the state with
lambda_eff written into its multiplier dofs (the adjoint refactorises the exact Q1P0
tangent there). Reference: Simo and Taylor, "Quasi-incompressible finite elasticity in
principal stretches", CMAME 85 (1991) 273-310 (the augmented Lagrangian on a mixed element).
"""

from __future__ import annotations

import dataclasses
import logging

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.solid import (KERNEL_CHUNK, SolidQ1P0, chunked, deformation_gradient, det3,
                              element_coeffs)
from eyefem.fem.terms import Term
from eyefem.solve.linsolve import positive_definite
from eyefem.solve.model import Model

log = logging.getLogger(__name__)

__all__ = ["AugmentedQ1P0", "augmented_model", "exact_model", "exact_state",
           "is_augmented", "solve_augmented", "uzawa_update", "volume_errors"]


def volume_change(u_loc, grad_n, dv):
    """g_e = integral (J - 1) dV (n,) mm^3 from element displacements u_loc (n, 24), dN/dX
    grad_n (n, 8, 8, 3) and Gauss point volumes dv (n, 8) mm^3."""
    F = deformation_gradient(u_loc.reshape(-1, 8, 3), grad_n)
    return jnp.sum(dv * (det3(F) - 1.0), axis=1)


_volume_change = jax.jit(volume_change)


@dataclasses.dataclass(frozen=True, eq=False)
class AugmentedQ1P0(Term):
    """The Q1P0 elements of ``exact`` with the augmented Lagrangian on their volume
    (module docstring): displacement dofs only (n, 24), the multipliers fixed estimates.

    Args:
      exact: the SolidQ1P0 term replaced (its name, params, geometry; its multiplier dofs
        are left to the solver to hold).
      lam: (n,) the multiplier estimates lambda_e^k, MPa.
      kappa: (n,) the penalties kappa_e, MPa.
      updates: Uzawa updates made so far (the load path's count, for the reports).
    """

    exact: SolidQ1P0
    lam: np.ndarray
    kappa: np.ndarray
    updates: int = 0
    multiplier_slots = ()
    chunked_kernel = True

    def __post_init__(self):
        e = self.exact
        n = e.dofs.shape[0]
        lam = np.asarray(self.lam, np.float64).reshape(-1)
        kappa = np.broadcast_to(np.asarray(self.kappa, np.float64), (n,)).copy()
        if lam.shape != (n,):
            raise ValueError(f"term '{e.name}': {lam.shape[0]} multiplier estimates for {n} "
                             "elements; give one per element")
        if not np.all(kappa > 0):
            raise ValueError(f"term '{e.name}': penalty kappa = {kappa.min():g} MPa; must be > 0 "
                             "(NewtonOptions.penalty_factor > 0, materials with c10 + c01 > 0)")
        object.__setattr__(self, "lam", lam)
        object.__setattr__(self, "kappa", kappa)
        object.__setattr__(self, "name", e.name)
        object.__setattr__(self, "dofs", e.dofs[:, :24])
        object.__setattr__(self, "params", e.params)
        object.__setattr__(self, "data", {**e.data, "lam": lam, "kappa": kappa,
                                          "vol": e.data["dv"].sum(axis=1)})

    @property
    def multiplier_dofs(self) -> np.ndarray:
        """(n,) the exact term's multiplier dofs (held at 0 in the augmented solve)."""
        return self.exact.dofs[:, 24]

    def local_energy(self, q_loc, params, data):
        g = volume_change(q_loc, data["grad_n"], data["dv"])
        q25 = jnp.concatenate([q_loc, data["lam"][:, None]], axis=1)
        return (SolidQ1P0.local_energy(self.exact, q25, params, data)
                + 0.5 * data["kappa"] * g * g / data["vol"])

    def _augmented_blocks(self, q_loc, params, data):
        """Gradients (n, 24) and Hessians (n, 24, 24): the Q1P0 blocks at lambda_eff plus
        kappa / (4 V) k_ul k_ul^T (module docstring)."""
        g = volume_change(q_loc, data["grad_n"], data["dv"])
        lam_eff = data["lam"] + 0.5 * data["kappa"] * g / data["vol"]
        q25 = jnp.concatenate([q_loc, lam_eff[:, None]], axis=1)
        gu, _, kuu, kul = SolidQ1P0._blocks(self.exact, q25, params, data)
        w = 0.25 * data["kappa"] / data["vol"]
        return gu, kuu + w[:, None, None] * kul[:, :, None] * kul[:, None, :]

    def local_grad_hess(self, q_loc, params, data):
        return self._augmented_blocks(q_loc, params, data)

    def grad_hess_condensed(self, q, params, data, dofs, beta):
        def one(data, dofs):
            return self._augmented_blocks(q[dofs], params, data)
        chunk = KERNEL_CHUNK.get(jax.default_backend())
        g, H = chunked(one, data, dofs, chunk)
        return g, H, None, None

    def multipliers(self, q) -> np.ndarray:
        """lambda_eff (n,) MPa at the global state q (n_dof,): the Q1P0 multipliers whose
        forces the penalty and the estimates exert together."""
        g = np.asarray(_volume_change(q[self.dofs], self.data["grad_n"], self.data["dv"]))
        return self.lam + 0.5 * self.kappa * g / self.data["vol"]

    def volume_errors(self, q) -> np.ndarray:
        """g_e / V_e = (Jbar_e - 1) (n,) at the global state q, dimensionless."""
        g = np.asarray(_volume_change(q[self.dofs], self.data["grad_n"], self.data["dv"]))
        return g / self.data["vol"]

    def fields(self, q, params):
        """The exact term's fields (SolidQ1P0.fields) at q with lambda_eff."""
        return self.exact.fields(_with_multipliers(q, self), params)

    def report(self, q, params) -> dict:
        return {"uzawa_updates": float(self.updates),
                "max_volume_error": float(np.max(np.abs(self.volume_errors(q))))}


def _with_multipliers(q, term: AugmentedQ1P0) -> np.ndarray:
    out = np.array(q, dtype=np.float64)
    out[term.multiplier_dofs] = term.multipliers(q)
    return out


def is_augmented(model: Model, active=None) -> bool:
    """Whether the model (its active terms) has augmented Q1P0 terms."""
    return any(isinstance(t, AugmentedQ1P0) for t in model._active(active))


def shear_moduli(term: SolidQ1P0) -> np.ndarray:
    """The elements' initial shear moduli 2 (c10 + c01) (n,) MPa (their coefficient tables,
    mixtures included: eyefem.fem.solid.element_coeffs)."""
    c = np.asarray(element_coeffs(np.asarray(term.params["coeffs"]), term.data))
    return 2.0 * (c[:, 1, 0] + c[:, 0, 1])


def augmented_model(model: Model, penalty_factor: float = 100.0, q=None) -> Model:
    """The model with each SolidQ1P0 term replaced by its :class:`AugmentedQ1P0` (kappa_e =
    penalty_factor x the element's shear modulus; the estimates from q's multiplier dofs,
    0 without q). Other terms are kept. A ValueError for a subclass of SolidQ1P0 (ANS,
    incompatible modes, viscoelastic, a shortened loop: their constraint is not this one)."""
    if not penalty_factor > 0:
        raise ValueError(f"NewtonOptions.penalty_factor = {penalty_factor}; must be > 0 "
                         "(default 100: kappa = 100 x the shear modulus)")
    terms = []
    for t in model.terms:
        if isinstance(t, SolidQ1P0) and type(t) is not SolidQ1P0:
            raise ValueError(f"term '{t.name}' ({type(t).__name__}): the augmented Lagrangian "
                             "supports the plain SolidQ1P0 element only; use "
                             "incompressibility = \"exact\"")
        if type(t) is SolidQ1P0:
            lam = np.zeros(len(t.dofs)) if q is None else np.asarray(q)[t.dofs[:, 24]]
            t = AugmentedQ1P0(t, lam, penalty_factor * shear_moduli(t))
        terms.append(t)
    return model.with_terms(terms)


def exact_model(model: Model) -> Model:
    """The model with each AugmentedQ1P0 term back to its SolidQ1P0 (the other terms as
    they are: a load path's hooks may have changed them)."""
    if not is_augmented(model):
        return model
    return model.with_terms([t.exact if isinstance(t, AugmentedQ1P0) else t
                             for t in model.terms])


def exact_state(model: Model, q) -> np.ndarray:
    """q (n_dof,) with each augmented term's lambda_eff in its multiplier dofs: the state
    of :func:`exact_model`."""
    out = np.array(q, dtype=np.float64)
    for t in model.terms:
        if isinstance(t, AugmentedQ1P0):
            out[t.multiplier_dofs] = t.multipliers(q)
    return out


def volume_errors(model: Model, q, active=None) -> float:
    """max_e |Jbar_e - 1| over the (active) augmented terms' elements at q (0: none)."""
    errs = [np.max(np.abs(t.volume_errors(q))) for t in model._active(active)
            if isinstance(t, AugmentedQ1P0)]
    return float(max(errs)) if errs else 0.0


UZAWA_UPDATES = {"updates": 0}
"""Uzawa updates made since start (all runs; read by benchmarks/bench_incompressibility.py)."""


def uzawa_update(model: Model, q, tol: float, active=None) -> Model | None:
    """The model with the (active) augmented terms' estimates updated to lambda_eff at q
    (one Uzawa step), or None where max_e |Jbar_e - 1| <= tol already."""
    err = volume_errors(model, q, active)
    if err <= tol:
        return None
    names = {t.name for t in model._active(active)}
    new = [dataclasses.replace(t, lam=t.multipliers(q), updates=t.updates + 1)
           if isinstance(t, AugmentedQ1P0) and t.name in names else t for t in model.terms]
    UZAWA_UPDATES["updates"] += 1
    log.debug("  Uzawa update: max |J - 1| = %.2e > %.1e", err, tol)
    return model.with_terms(new)


def _held(stage, dofs):
    """The stage with ``dofs`` also prescribed, at 0."""
    d, v = stage.prescribed
    keep = ~np.isin(dofs, d)
    return dataclasses.replace(stage, prescribed=(np.concatenate([d, dofs[keep]]),
                                                  np.concatenate([v, np.zeros(keep.sum())])))


def solve_augmented(model: Model, stages, *, run, q0=None, theta=None, options, on_step=None,
                    on_stage_end=None, completed=()):
    """``run`` (eyefem.solve.loadpath.solve, which calls this) with the augmented Lagrangian
    on the Q1P0 terms (module docstring); the same arguments and result. ``on_step``,
    ``on_stage_end`` and the
    Solution see the exact model and state (lambda_eff in the multiplier dofs); the
    starts handed to ``on_stage_end`` and a ConvergenceError's state hold the
    displacements with the multipliers at 0 (a resumed run starts its estimates there)."""
    from eyefem.solve.assembly import Assembler
    from eyefem.solve.records import Solution

    q = np.zeros(model.n_dof) if q0 is None else np.array(q0, dtype=np.float64)
    aug = augmented_model(model, options.penalty_factor, q)
    held = np.concatenate([t.multiplier_dofs for t in aug.terms
                           if isinstance(t, AugmentedQ1P0)]).astype(np.int64)
    q[held] = 0.0
    stages = [_held(s, held) for s in stages]

    def step(rec, m, qs, th):
        on_step(rec, exact_model(m), exact_state(m, qs), th)

    def stage_end(i, m, qs, th, starts):
        on_stage_end(i, exact_model(m), exact_state(m, qs), th, starts)

    options = dataclasses.replace(options, backend=positive_definite(options.backend))
    sol = run(aug, stages, q0=q, theta=theta, options=options,
              on_step=None if on_step is None else step,
              on_stage_end=None if on_stage_end is None else stage_end, completed=completed)
    log.info("augmented Lagrangian: %d Uzawa updates, max |J - 1| = %.2e at the end",
             uzawa_updates(sol.model), volume_errors(sol.model, sol.q))
    exact = exact_model(sol.model)
    prescribed = np.zeros(exact.n_dof, bool)
    if stages:
        prescribed[stages[-1].prescribed[0]] = True
    prescribed[held] = False
    return Solution(exact, exact_state(sol.model, sol.q), sol.theta, sol.history,
                    Assembler(exact, prescribed, beta=options.beta), None, sol.active)



def uzawa_updates(model: Model) -> int:
    """Uzawa updates made by the model's augmented terms (the largest count of any)."""
    return max([t.updates for t in model.terms if isinstance(t, AugmentedQ1P0)], default=0)

"""Quasi-linear viscoelastic Q1P0 hexahedra: the tissue's elastic law relaxing with a Prony
series (issue 74, item 3), as the incremental energy of a time step.

**The law** (Simo 1987; Holzapfel, "Nonlinear solid mechanics", 2000, sec. 6.10; FEBio's
``uncoupled viscoelastic`` material, FEUncoupledViscoElasticMaterial). The isochoric
second Piola-Kirchhoff stress is a hereditary integral of the elastic one,

    S(t) = -p J C^-1 + integral_{-inf}^t G(t - s) dS0/ds ds,
    G(t) = g_inf + sum_i g_i exp(-t / tau_i),      g_inf = 1 - sum_i g_i,

with S0(C) = 2 dW(Ibar1, Ibar2)/dC the isochoric stress of the tissue's generalised
Mooney-Rivlin law W (eyefem.fem.materials; its reduced invariants make S0 deviatoric
and zero at C = I). The instantaneous response (G(0) = 1) is the elastic law; the
equilibrium response (G(inf)) is g_inf times it. In internal variables,
S = -p J C^-1 + g_inf S0 + sum_i h_i with dh_i/dt + h_i / tau_i = g_i dS0/dt.

**The step** (exact exponential integration with S0 linear in time over the step,
FEBio's update): over a step of dt minutes from the converged state n,

    h_i^{n+1} = e_i h_i^n + g_i b_i (S0(C_{n+1}) - S0(C_n)),
    e_i = exp(-dt / tau_i),  b_i = (1 - e_i) tau_i / dt  (b_i = 1 at dt = 0),

so the step's stress is S_{n+1} = c_n S0(C_{n+1}) + A_n - p J C^-1 with the scalar
c_n = g_inf + sum_i g_i b_i and the constant (per Gauss point) tensor
A_n = sum_i (e_i h_i^n - g_i b_i S0(C_n)). That is the derivative 2 dpsi/dC of the
step's energy density

    psi_{n+1}(F) = c_n W(Ibar1, Ibar2) + A_n : E + 2 lambda (J - 1),   E = (F^T F - I)/2,

a potential of the step: the element's energy is the elastic Q1P0 element's with its
coefficients scaled by c_n plus sum_g dv A_n : E, so Newton's tangent is symmetric and
autodiff, the adjoint and gradients through time (eyefem.solve.transient) carry over.
psi is objective (A_n is a material tensor, E invariant under F -> Q F). The update is
exact where S0 is constant over a step (relaxation at a held stretch, any dt) and
second-order accurate otherwise. A step of dt = 0 (a stage without a duration) is
instantaneous: c = 1, h_i^{n+1} - h_i^n = g_i (S0_{n+1} - S0_n), the elastic response
about the state reached.

**History** (params of the term, :attr:`history_keys`, carried by the load path,
:class:`eyefem.solve.loadpath.Stage`): ``h`` (n_elem, 8, n_terms, 3, 3) MPa, the
internal stresses per element and Gauss point; ``s_prev`` (n_elem, 8, 3, 3) MPa, S0 at
the last converged step; ``time`` (minutes). The load path sets ``dt`` (minutes) from
the stage's duration and calls :meth:`ViscoelasticQ1P0.advance` after each converged
step; :meth:`ViscoelasticQ1P0.history_after` is the same update in JAX (differentiable).

**Constants** (params): ``g`` (n_materials, n_terms) and ``tau`` (n_materials, n_terms,
minutes) per material, beside the elastic ``coeffs``; a material with g = 0 is elastic.
An element cut by a tissue boundary (``mesh.material_fractions``) takes the volume
fractions' weighted g_i and tau_i for its mixed energy (an approximation at the limbus).

FEBio's ``viscoelastic`` material has G(t) = 1 + sum gamma_i exp(-t/tau_i) about its
elastic (equilibrium) law: the same material is FEBio's with the elastic coefficients
scaled by g_inf and gamma_i = g_i / g_inf.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.materials import strain_energy
from eyefem.fem.solid import (SolidQ1P0, deformation_gradient, det3, element_coeffs,
                              element_fields)


def prony_factors(dt, tau):
    """e = exp(-dt / tau) and b = (1 - e) tau / dt (1 at dt = 0) of a step of dt minutes,
    elementwise over tau (minutes, > 0); smooth in dt and tau."""
    x = dt / tau
    small = x < 1e-6
    xs = jnp.where(small, 1.0, x)
    e = jnp.exp(-x)
    b = jnp.where(small, 1.0 - 0.5 * x + x * x / 6.0, -jnp.expm1(-xs) / xs)
    return e, b


def relaxation(t, g, tau):
    """The reduced relaxation function G(t) = 1 - sum g_i + sum g_i exp(-t / tau_i)
    (numpy; t (...,), g and tau (n_terms,))."""
    t = np.asarray(t, float)[..., None]
    g, tau = np.asarray(g, float), np.asarray(tau, float)
    return 1.0 - g.sum() + np.sum(g * np.exp(-t / tau), axis=-1)


def isochoric_stress(C, coeffs):
    """S0 = 2 dW(Ibar1, Ibar2)/dC (..., 3, 3), MPa, of right Cauchy-Green tensors C (..., 3, 3)
    and coefficient tables (..., 4, 4): deviatoric (S0 : C = 0) and zero at C = I."""
    def w(c, k):
        J2 = det3(c)  # J^2
        i1 = jnp.trace(c)
        i2 = 0.5 * (i1 * i1 - jnp.sum(c * c))
        return strain_energy(J2 ** (-1.0 / 3.0) * i1, J2 ** (-2.0 / 3.0) * i2, k)
    f = jax.grad(w)
    for _ in range(C.ndim - 2):
        f = jax.vmap(f)
    S = 2.0 * f(C, coeffs)
    return 0.5 * (S + jnp.swapaxes(S, -1, -2))


def _point_coeffs(params, data):
    """Per element: the coefficient tables (n, 4, 4), g (n, m) and tau (n, m)."""
    c = element_coeffs(params["coeffs"], data)
    g, tau = jnp.asarray(params["g"]), jnp.asarray(params["tau"])
    if "mix" in data:
        return c, data["mix"] @ g, data["mix"] @ tau
    return c, g[data["mat"]], tau[data["mat"]]


def step_constants(params, data):
    """(c (n,), A (n, 8, 3, 3), e (n, m), b (n, m), g (n, m), coeffs (n, 4, 4)) of the
    step: c_n = g_inf + sum g_i b_i, A_n = sum_i (e_i h_i - g_i b_i S0_n)."""
    coeffs, g, tau = _point_coeffs(params, data)
    e, b = prony_factors(params["dt"], tau)
    c = 1.0 - jnp.sum(g, axis=1) + jnp.sum(g * b, axis=1)
    A = (jnp.einsum("em,egmij->egij", e, params["h"])
         - jnp.sum(g * b, axis=1)[:, None, None, None] * params["s_prev"])
    return c, A, e, b, g, coeffs


@dataclasses.dataclass(frozen=True, eq=False)
class ViscoelasticQ1P0(SolidQ1P0):
    """Q1P0 incompressible elements of quasi-linear viscoelastic tissues (module docstring).

    Args: as :class:`eyefem.fem.solid.SolidQ1P0`, and
      g: (n_materials, n_terms) Prony fractions g_i (>= 0, sum < 1 per material; a row of
        zeros: an elastic material).
      tau: (n_materials, n_terms) time constants tau_i, minutes (> 0).
    """

    g: np.ndarray = None
    tau: np.ndarray = None
    chunked_kernel = False  # the history params are per element (not chunked with data)
    history_keys = ("h", "s_prev", "time")

    def __post_init__(self):
        super().__post_init__()
        n_mat = len(self.mesh.materials)
        g = np.atleast_2d(np.asarray(self.g, np.float64))
        tau = np.atleast_2d(np.asarray(self.tau, np.float64))
        if g.shape[0] == 1 and n_mat > 1:
            g = np.repeat(g, n_mat, 0)
        if tau.shape[0] == 1 and n_mat > 1:
            tau = np.repeat(tau, n_mat, 0)
        if g.shape != tau.shape or g.shape[0] != n_mat:
            raise ValueError(f"term '{self.name}': g {g.shape} and tau {tau.shape}; expected "
                             f"({n_mat}, n_terms) each, one row per material {self.mesh.materials}")
        if (not np.all(np.isfinite(g)) or np.any(g < 0) or np.any(g.sum(1) >= 1.0)
                or not np.all(np.isfinite(tau)) or np.any(tau <= 0)):
            raise ValueError(f"term '{self.name}': Prony constants g = {g.tolist()}, tau = "
                             f"{tau.tolist()} min; need g_i >= 0 with sum g_i < 1 per material "
                             "and tau_i > 0")
        n, m = len(self.elements), g.shape[1]
        p = dict(self.params)
        p.update(g=g, tau=tau, dt=0.0, time=0.0, h=np.zeros((n, 8, m, 3, 3)),
                 s_prev=np.zeros((n, 8, 3, 3)))
        object.__setattr__(self, "g", g)
        object.__setattr__(self, "tau", tau)
        object.__setattr__(self, "params", p)

    # --- the step's energy --------------------------------------------------------------
    @staticmethod
    def _scaled(params, data, c):
        """The elastic element's params and data with every element's coefficients scaled
        by c (n,): W is linear in c_rs, so the element mixture carries the factor."""
        n_mat = params["coeffs"].shape[0]
        mix = data["mix"] if "mix" in data else jax.nn.one_hot(data["mat"], n_mat)
        return {"coeffs": params["coeffs"]}, {**data, "mix": mix * c[:, None]}

    def local_energy(self, q_loc, params, data):
        c, A, *_ = step_constants(params, data)
        p0, d0 = self._scaled(params, data, c)
        e = SolidQ1P0.local_energy(self, q_loc, p0, d0)
        F = deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), data["grad_n"])
        E = 0.5 * (jnp.swapaxes(F, -1, -2) @ F - jnp.eye(3))
        return e + jnp.einsum("eg,egij,egij->e", data["dv"], A, E)

    def _blocks(self, q_loc, params, data):
        """The elastic element's blocks with coefficients scaled by c_n, plus those of
        sum_g dv A : E: g_u[a i] = dv (F A)_iJ G_aJ, K[a i, b k] = delta_ik dv G_aJ A_JL G_bL."""
        c, A, *_ = step_constants(params, data)
        p0, d0 = self._scaled(params, data, c)
        gu, gl, kuu, kul = SolidQ1P0._blocks(self, q_loc, p0, d0)
        G, dv = data["grad_n"], data["dv"]
        F = deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), G)
        gu = gu + jnp.einsum("eg,egij,egjk,egak->eai", dv, F, A, G).reshape(-1, 24)
        kab = jnp.einsum("eg,egaj,egjl,egbl->eab", dv, G, A, G)
        kuu = kuu + jnp.einsum("eab,ik->eaibk", kab, jnp.eye(3)).reshape(-1, 24, 24)
        return gu, gl, kuu, kul

    # --- history ------------------------------------------------------------------------
    def history_after(self, q, params) -> dict:
        """The history after a converged step at q (JAX, differentiable in q and params):
        h_i <- e_i h_i + g_i b_i (S0(C) - S0_prev), s_prev <- S0(C), time <- time + dt."""
        q_loc = q[self.dofs]
        return _history(q_loc, params, self.data)

    def advance(self, q, params) -> dict:
        """The params after a converged step (numpy): the new history, dt back to 0."""
        new = _history_jit(jnp.asarray(np.asarray(q)[self.dofs]), params, self.data)
        return {**params, "h": np.asarray(new["h"]), "s_prev": np.asarray(new["s_prev"]),
                "time": float(new["time"]), "dt": 0.0}

    # --- outputs ------------------------------------------------------------------------
    def fields(self, q, params):
        """As :meth:`SolidQ1P0.fields`, with the viscoelastic stress of the step (or of the
        converged state, with dt = 0 and its advanced history)."""
        q_loc = jnp.asarray(np.asarray(q)[self.dofs])
        sig, J, lam, E = _point_fields_jit(q_loc, params, self.data)
        return element_fields(*(np.asarray(a) for a in (sig, J, lam, E)), self.data["dv"])

    def report(self, q, params) -> dict:
        return {"time_min": float(params["time"]) + float(params["dt"])}


def _history(q_loc, params, data):
    _, _, e, b, g, coeffs = step_constants(params, data)
    F = deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), data["grad_n"])
    C = jnp.swapaxes(F, -1, -2) @ F
    S0 = isochoric_stress(C, jnp.broadcast_to(coeffs[:, None], C.shape[:2] + (4, 4)))
    h = (e[:, None, :, None, None] * params["h"]
         + (g * b)[:, None, :, None, None] * (S0 - params["s_prev"])[:, :, None])
    return {"h": h, "s_prev": S0, "time": params["time"] + params["dt"]}


_history_jit = jax.jit(_history)


def history_at(q, params, data, dofs) -> dict:
    """:meth:`ViscoelasticQ1P0.history_after` of a term given by its ``data`` and ``dofs``
    (JAX, differentiable in q (n_dof,) and params): what a staged adjoint's carry hands on
    (eyefem.eye.simulators.TimelineSimulator), the term's arrays passed as data so that one
    compiled function serves every design."""
    return _history(q[dofs], params, data)


@jax.jit
def _point_fields_jit(q_loc, params, data):
    """Cauchy stress (n, 8, 3, 3), J (n, 8), lambda (n,), Green-Lagrange strain (n, 8, 3, 3)."""
    c, A, _, _, _, coeffs = step_constants(params, data)
    F = deformation_gradient(q_loc[:, :24].reshape(-1, 8, 3), data["grad_n"])
    lam = q_loc[:, 24]

    def energy(F_, lam_, c_, k_, A_):
        J = det3(F_)
        C = F_.T @ F_
        i1 = jnp.trace(C)
        i2 = 0.5 * (i1 * i1 - jnp.sum(C * C))
        return (c_ * strain_energy(J ** (-2.0 / 3.0) * i1, J ** (-4.0 / 3.0) * i2, k_)
                + 2.0 * lam_ * (J - 1.0) + jnp.sum(A_ * 0.5 * (C - jnp.eye(3))))

    P = jax.vmap(jax.vmap(jax.grad(energy), (0, None, None, None, 0)), (0, 0, 0, 0, 0))(
        F, lam, c, coeffs, A)
    J = det3(F)
    sig = jnp.einsum("egij,egkj->egik", P, F) / J[..., None, None]
    E = 0.5 * (jnp.einsum("egki,egkj->egij", F, F) - jnp.eye(3))
    return sig, J, lam, E

"""A model: a mesh, its energy terms and the dof layout, with compiled kernels.

Global dof vector q (n_dof,): nodal displacements u (3 per node, node-major, mm),
then one multiplier per solid element (MPa), then any extra unknowns terms declare.
The design pytree ``theta`` maps each term name to its params.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.mesh import Mesh
from eyefem.fem.solid import chunked_sum
from eyefem.fem.terms import Term

log = logging.getLogger(__name__)

_KERNELS: dict = {}


def check_x64():
    """Raise unless JAX runs in float64 (entry points enable it)."""
    if jnp.zeros(1).dtype != jnp.float64:
        raise RuntimeError("eyefem needs float64: call jax.config.update('jax_enable_x64', True) "
                           "before building a model (the eyefem CLI and tests do)")


@dataclasses.dataclass(frozen=True, eq=False)
class Model:
    """Mesh + energy terms + dof layout.

    Attributes:
      mesh: the mesh (all bodies).
      terms: energy terms, unique names.
      n_dof: size of q.
      multiplier_dofs: (m,) dofs that are Lagrange multipliers.
    """

    mesh: Mesh
    terms: tuple[Term, ...]
    n_dof: int

    def __post_init__(self):
        names = [t.name for t in self.terms]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"model terms: duplicate names {sorted(dup)}; every term needs its own")
        for t in self.terms:
            if t.dofs.size and (t.dofs.min() < 0 or t.dofs.max() >= self.n_dof):
                raise ValueError(f"term '{t.name}': dof indices outside [0, {self.n_dof})")
        object.__setattr__(self, "terms", tuple(self.terms))

    @property
    def n_u(self) -> int:
        return 3 * self.mesh.n_nodes

    @property
    def multiplier_dofs(self) -> np.ndarray:
        out = [t.dofs[:, list(t.multiplier_slots)].ravel() for t in self.terms if t.multiplier_slots]
        return np.unique(np.concatenate(out)) if out else np.zeros(0, np.int64)

    def term(self, name: str) -> Term:
        for t in self.terms:
            if t.name == name:
                return t
        raise KeyError(f"no term '{name}'; the model has {[t.name for t in self.terms]}")

    def theta0(self) -> dict:
        """The default design pytree: term name -> params."""
        return {t.name: t.params for t in self.terms}

    def with_terms(self, terms: Sequence[Term]) -> "Model":
        """A copy with other terms (kernels of unchanged term classes are recompiled lazily)."""
        return Model(self.mesh, tuple(terms), self.n_dof)

    # --- compiled kernels -------------------------------------------------------------
    def _kernel(self, term: Term, kind: str):
        """Compiled kernel shared by all terms of one class and static key.

        Kernels read arrays only from their arguments (q, params, data, dofs), so the
        first instance of a class serves as the prototype of every later one.
        """
        key = (type(term), kind, term.static_key())
        ks = _KERNELS
        if key not in ks:
            if kind == "grad_hess":
                ks[key] = jax.jit(term.grad_hess)
            elif kind == "grad_hess_condensed":
                ks[key] = jax.jit(term.grad_hess_condensed)
            elif kind == "grad_hess_gauss_newton":
                ks[key] = jax.jit(term.grad_hess_gauss_newton)
            elif kind == "energy":
                ks[key] = jax.jit(lambda q, p, d, dofs: term.energy(q, p, d, dofs))
            elif kind == "grad":
                ks[key] = jax.jit(_residual(term))
            elif kind == "lookahead":
                ks[key] = jax.jit(lambda q, dq, p, d, dofs: term.gap_linearisation(q[dofs], dq[dofs], p, d))
            elif kind == "hvp":
                ks[key] = jax.jit(_hvp(term))
            elif kind == "hvp_many":
                ks[key] = jax.jit(_over_chunks(term, jax.vmap(
                    _hvp(term), in_axes=(None, 1, None, None, None), out_axes=1)))
            elif kind == "params_vjp_many":
                ks[key] = jax.jit(_over_chunks(term, jax.vmap(
                    _params_vjp(term), in_axes=(None, 1, None, None, None))))
        return ks[key]

    def energy(self, q, theta, active=None) -> float:
        """Total potential energy (N mm) at q for the design theta; a ValueError if an
        active term is not a potential (:func:`non_potential`)."""
        loads = non_potential(self._active(active))
        if loads:
            raise ValueError(f"the model has no total energy: {loads} are follower loads "
                             "that are not potentials (their residuals are exact)")
        return float(sum(self._kernel(t, "energy")(q, theta[t.name], t.data, t.dofs)
                         for t in self._active(active)))

    def gradient(self, q, theta, active=None) -> np.ndarray:
        """Residual dPi/dq (n_dof,) (internal minus external forces; constraint values);
        a term that is not a potential adds its own residual (:func:`non_potential`)."""
        return self.gradient_and_load(q, theta, None, active)[0]

    def gradient_and_load(self, q, theta, dofs, active=None) -> tuple[np.ndarray, float]:
        """The residual (n_dof,) as :meth:`gradient`, and the load the state carries on
        ``dofs`` (N; 0 for None): the largest norm over the terms of a term's force on those
        dofs (at equilibrium the forces of the terms balance, and the largest of them is
        the scale of the forces in play, whatever the step's first residual was)."""
        r, load = np.zeros(self.n_dof), 0.0
        for t in self._active(active):
            g = np.asarray(self._kernel(t, "grad")(q, theta[t.name], t.data, t.dofs))
            if dofs is not None:
                load = max(load, _norm(g[dofs]))
            r += g
        return r, load

    def hvp(self, q, v, theta, active=None) -> np.ndarray:
        """Tangent-vector product K v (n_dof,) by forward-over-reverse autodiff."""
        r = np.zeros(self.n_dof)
        for t in self._active(active):
            r += np.asarray(self._kernel(t, "hvp")(q, v, theta[t.name], t.data, t.dofs))
        return r

    def hvp_many(self, q, V, theta, active=None) -> np.ndarray:
        """K V (n_dof, k) for k vectors V (n_dof, k) at once (:meth:`hvp`, vectorised)."""
        r = np.zeros((self.n_dof, V.shape[1]))
        for t in self._active(active):
            r += np.asarray(self._kernel(t, "hvp_many")(q, V, theta[t.name], t.data, t.dofs))
        return r

    def params_vjp_many(self, q, L, theta, active=None) -> list[dict]:
        """The residual's vector-Jacobian products with respect to the design: for each
        column l of L (n_dof, k), d(l . R(q, theta))/dtheta as a pytree like theta (the
        active terms' params; others zero). Compiled per term class, all columns at once."""
        k = L.shape[1]
        out = [{} for _ in range(k)]
        names = {t.name for t in self._active(active)}
        for t in self.terms:
            if t.name in names:
                g = jax.tree_util.tree_map(np.asarray, self._kernel(t, "params_vjp_many")(
                    q, L, theta[t.name], t.data, t.dofs))  # to the host once, then sliced
                for j in range(k):
                    out[j][t.name] = jax.tree_util.tree_map(lambda a, j=j: a[j], g)
            else:
                zero = jax.tree_util.tree_map(lambda a: np.zeros(np.shape(a)), theta[t.name])
                for j in range(k):
                    out[j][t.name] = zero
        return out

    def gap_linearisations(self, q, dq, theta, active=None) -> list:
        """(term, g (n,), dg (n,), dg/dq_loc (n, k), gap at q + dq (n,)) of every active
        penalty-contact term (``Term.gap_linearisation``) at q along the step dq (numpy)."""
        out = []
        for t in self._active(active):
            if type(t).gap_linearisation is Term.gap_linearisation:
                continue
            lin = self._kernel(t, "lookahead")(q, dq, theta[t.name], t.data, t.dofs)
            out.append((t, *(np.asarray(a) for a in lin)))
        return out

    def local_grad_hess(self, term: Term, q, theta):
        """Local gradients and Hessians of one term at q (numpy)."""
        g, H = self._kernel(term, "grad_hess")(q, theta[term.name], term.data, term.dofs)
        return np.asarray(g), np.asarray(H)

    def local_grad_hess_gauss_newton(self, term: Term, q, theta):
        """Local gradients and Gauss-Newton Hessians (``Term.grad_hess_gauss_newton``)."""
        g, H = self._kernel(term, "grad_hess_gauss_newton")(q, theta[term.name], term.data,
                                                             term.dofs)
        return np.asarray(g), np.asarray(H)

    def local_grad_hess_condensed(self, term: Term, q, theta, beta):
        """Local gradients (n, k) and primal Hessians with the multiplier condensed.

        Returns g (n, k), H_pp + d b b^T (n, k_p, k_p), b (n, k_p), d (n,) where b is the
        multiplier column and d = beta |mean diag H_pp| / |b|^2 (see linsolve); b and d
        are None for a term without multipliers.
        """
        out = self._kernel(term, "grad_hess_condensed")(q, theta[term.name], term.data,
                                                        term.dofs, beta)
        return tuple(None if a is None else np.asarray(a) for a in out)

    def update(self, q, theta) -> "Model":
        """The model with every term's host-side update applied at q (contact search)."""
        new = tuple(t.update(q, theta[t.name]) for t in self.terms)
        if all(a is b for a, b in zip(new, self.terms)):
            return self
        return Model(self.mesh, new, self.n_dof)

    def report(self, q, theta, active=None) -> dict:
        """Scalar outputs of every (active) term, keyed 'term/quantity'."""
        out = {}
        for t in self._active(active):
            for k, v in t.report(q, theta[t.name]).items():
                out[f"{t.name}/{k}"] = v
        return out

    def _active(self, active):
        if active is None:
            return self.terms
        return [t for t in self.terms if t.name in active]


def _norm(v) -> float:
    """Euclidean norm of v without overflow: a line-search trial near an inverted element
    can carry a term's forces beyond 1e154 N, whose squares overflow."""
    with np.errstate(over="ignore"):
        n = float(np.linalg.norm(v))
    if np.isfinite(n):
        return n
    m = float(np.max(np.abs(v)))
    return m * float(np.linalg.norm(v / m)) if np.isfinite(m) and m > 0 else m


def non_potential(terms) -> list[str]:
    """Names of the terms that are not potentials (``potential`` False: a follower pressure
    on an open surface, eyefem.fem.surface.FollowerPressure): their residual is their own
    ``residual(q, params, data, dofs)``, not an energy's gradient, and their tangent is not
    symmetric."""
    return [t.name for t in terms if not getattr(t, "potential", True)]


def _residual(term: Term):
    """(q, params, data, dofs) -> the residual (n_dof,) of one term: the gradient of its
    energy, or its own ``residual`` where it is not a potential (:func:`non_potential`)."""
    if not getattr(term, "potential", True):
        return term.residual
    return jax.grad(lambda q, p, d, dofs: term.energy(q, p, d, dofs))


def _hvp(term: Term):
    """(q, v, params, data, dofs) -> K v of one term (K = dR/dq, exact, also where it is
    not symmetric), forward over reverse."""
    g = _residual(term)
    return lambda q, v, p, d, dofs: jax.jvp(lambda x: g(x, p, d, dofs), (q,), (v,))[1]


SUM_CHUNK = {"cpu": 500}
"""Items per chunk of the adjoint's kernels (:meth:`Model.hvp_many`,
:meth:`Model.params_vjp_many`: sums over the items, vectorised over k columns) for terms
that allow it (``chunked_kernel``), per JAX backend (absent: one chunk). On the default
eye's solid (11,862 hexahedra) the design derivative of 8 columns took 0.10 s in chunks of
500 against 0.26 s at once, 2 tangent-vector products 0.08 s against 0.15 s (medians of
9, 2-core machine; docs/performance.md, "The adjoint's kernels in chunks")."""


def _over_chunks(term: Term, fn):
    """fn(q, v, params, data, dofs), a sum over the term's items, evaluated over chunks of
    SUM_CHUNK items in turn (:func:`eyefem.fem.solid.chunked_sum`) where the term's data
    holds per-item arrays only (``chunked_kernel``); fn itself otherwise."""
    if not getattr(term, "chunked_kernel", False):
        return fn

    def over_chunks(q, v, p, d, dofs):
        return chunked_sum(lambda d_, dofs_: fn(q, v, p, d_, dofs_), d, dofs,
                           SUM_CHUNK.get(jax.default_backend()))
    return over_chunks


def _params_vjp(term: Term):
    """(q, l, params, data, dofs) -> d(l . R)/dparams of one term, R its residual (reverse
    over forward: the directional derivative of the energy along l, differentiated in
    params; l . R itself where the term is not a potential)."""
    potential = getattr(term, "potential", True)

    def f(q, lam, p, d, dofs):
        def along(pp):
            if not potential:
                return jnp.dot(lam, term.residual(q, pp, d, dofs))
            return jax.jvp(lambda x: term.energy(x, pp, d, dofs), (q,), (lam,))[1]
        _, vjp = jax.vjp(along, p)
        return vjp(jnp.ones(()))[0]
    return f


def node_dofs(node_ids, components="xyz") -> np.ndarray:
    """Displacement dof indices (n * len(components),) of nodes for components among 'xyz'."""
    comp = ["xyz".index(c) for c in components]
    return (3 * np.asarray(node_ids, np.int64)[:, None] + np.asarray(comp)).ravel()


def prony_tables(material_names, prony: dict) -> tuple[np.ndarray, np.ndarray]:
    """Prony tables g (n_materials, m) and tau (n_materials, m, minutes) of
    :class:`eyefem.fem.viscoelastic.ViscoelasticQ1P0`, rows ordered like ``material_names``.

    ``prony``: material -> (g (k,), tau (k,) minutes) for the materials that relax; a
    material absent from it is elastic (g = 0). Shorter series are padded with g = 0 terms;
    an elastic row and a padded term take the first relaxing material's time constants, so
    that an element mixing a relaxing and an elastic tissue (``mesh.material_fractions``)
    keeps the relaxing tissue's tau_i with its fraction-weighted g_i. ValueError naming the
    material for a name the mesh lacks or constants that are not a Prony series."""
    names = list(material_names)
    unknown = sorted(set(prony) - set(names))
    if unknown:
        raise ValueError(f"prony: materials {unknown} are not in the mesh; it has {names}")
    if not prony:
        raise ValueError("prony: no material relaxes; give material -> (g, tau) or leave "
                         "prony out for an elastic solid")
    rows = {}
    for m, (g, tau) in prony.items():
        g = np.atleast_1d(np.asarray(g, np.float64))
        tau = np.atleast_1d(np.asarray(tau, np.float64))
        if g.ndim != 1 or g.shape != tau.shape or len(g) == 0:
            raise ValueError(f"prony['{m}']: g {g.shape} and tau {tau.shape}; expected two "
                             "equal-length lists (fractions, minutes)")
        if (not np.all(np.isfinite(g)) or np.any(g < 0) or g.sum() >= 1.0
                or not np.all(np.isfinite(tau)) or np.any(tau <= 0)):
            raise ValueError(f"prony['{m}']: g = {g.tolist()}, tau = {tau.tolist()} min; need "
                             "g_i >= 0 with sum g_i < 1 and tau_i > 0")
        rows[m] = (g, tau)
    n_terms = max(len(g) for g, _ in rows.values())
    first = next(m for m in names if m in rows)
    tau_fill = np.resize(rows[first][1], n_terms)
    G = np.zeros((len(names), n_terms))
    T = np.tile(tau_fill, (len(names), 1))
    for i, m in enumerate(names):
        if m in rows:
            g, tau = rows[m]
            G[i, :len(g)] = g
            T[i, :len(tau)] = tau
    return G, T


def with_viscoelastic(model: Model, prony: dict, name: str = "solid") -> Model:
    """The model with its Q1P0 solid term ``name`` replaced by
    :class:`eyefem.fem.viscoelastic.ViscoelasticQ1P0` on the same elements, multipliers and
    elastic coefficients, relaxing as ``prony`` says (:func:`prony_tables`; the materials it
    leaves out stay elastic). The instantaneous response is the elastic term's. ValueError
    for a solid term of another element (assumed shear strains, compressible materials)."""
    from eyefem.fem.solid import SolidQ1P0
    from eyefem.fem.viscoelastic import ViscoelasticQ1P0

    s = model.term(name)
    if type(s) is not SolidQ1P0:
        raise ValueError(f"term '{name}' is a {type(s).__name__}; the viscoelastic element is "
                         "the Q1P0 brick (wall_element = 'q1p0', exactly incompressible "
                         "materials)")
    g, tau = prony_tables(s.mesh.materials, prony)
    visco = ViscoelasticQ1P0(s.name, s.mesh, s.coeffs, s.multiplier_offset,
                             elements=s.elements, g=g, tau=tau)
    return model.with_terms([visco if t is s else t for t in model.terms])


def solid_model(mesh: Mesh, materials: dict, extra_terms=(), n_extra_dofs: int = 0,
                name: str = "solid", prony: dict | None = None) -> Model:
    """A model of the mesh's Q1P0 solid plus further terms.

    Args:
      mesh: the mesh; every name in ``mesh.materials`` must be a key of ``materials``.
      materials: name -> MooneyRivlin (exactly incompressible: the Q1P0 element), or one of
        FEBio's laws with a volumetric energy (eyefem.fem.materials.UncoupledMooneyRivlin,
        CoupledMooneyRivlin: the displacement element of eyefem.fem.solid_compressible).
      extra_terms: further Term objects (their dofs index the same q).
      n_extra_dofs: unknowns beyond displacements and multipliers.
      prony: optional material -> (g (k,), tau (k,) minutes): those materials relax as a
        quasi-linear viscoelastic Prony series (:func:`with_viscoelastic`; the solid term is
        then a ViscoelasticQ1P0 whose instantaneous response is the elastic law); None:
        elastic. Exactly incompressible materials only.

    With only incompressible materials (the default of case files and the eye) the model
    is the Q1P0 term ``name`` on every element and one multiplier per element. Otherwise
    the elements of compressible materials form a SolidCompressible term (named ``name``
    where it holds every element, else ``name + "_compressible"``) and only the others
    carry multipliers (one per Q1P0 element, after the displacements).
    """
    from eyefem.fem.materials import bulk_modulus, coupled_constants, is_compressible
    from eyefem.fem.solid import SolidQ1P0

    missing = [m for m in mesh.materials if m not in materials]
    if missing:
        raise ValueError(f"materials {missing} are used by the mesh but not defined; "
                         f"defined: {sorted(materials)}")
    coeffs = np.stack([materials[m].coeffs for m in mesh.materials])
    n_u = 3 * mesh.n_nodes
    comp = np.array([is_compressible(materials[m]) for m in mesh.materials], bool)
    if not comp.any():
        solid = SolidQ1P0(name, mesh, coeffs, multiplier_offset=n_u)
        model = Model(mesh, (solid, *extra_terms), n_u + mesh.n_elem + n_extra_dofs)
        return model if prony is None else with_viscoelastic(model, prony, name)
    if prony is not None:
        raise ValueError(f"prony: materials {[m for m, c in zip(mesh.materials, comp) if c]} "
                         "have a bulk modulus; the viscoelastic element is the exactly "
                         "incompressible Q1P0 brick")
    from eyefem.fem.solid_compressible import SolidCompressible

    if mesh.material_fractions is not None:
        used = np.asarray(mesh.material_fractions) > 0
        on = used[:, comp].any(axis=1)
        mixed = on & used[:, ~comp].any(axis=1)
        if mixed.any():
            raise ValueError(f"element {int(np.nonzero(mixed)[0][0])}: its volume fractions mix "
                             "an exactly incompressible material with one that has a bulk "
                             "modulus; give every material of a mixed element the same form")
    else:
        on = comp[mesh.material_ids]
    k = np.array([bulk_modulus(materials[m]) for m in mesh.materials])
    cc = np.stack([coupled_constants(materials[m]) for m in mesh.materials])
    inc = np.nonzero(~on)[0]
    terms = []
    if len(inc):
        terms.append(SolidQ1P0(name, mesh, coeffs, multiplier_offset=n_u, elements=inc))
    terms.append(SolidCompressible(name if not len(inc) else f"{name}_compressible", mesh,
                                   coeffs, k, cc, elements=np.nonzero(on)[0]))
    return Model(mesh, (*terms, *extra_terms), n_u + len(inc) + n_extra_dofs)

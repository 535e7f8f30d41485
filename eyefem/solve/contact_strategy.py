"""Contact strategy of Newton's method: when the contact pairing (dynamic terms) is
re-paired or frozen, when a state converged with frozen pairs stands, and the
active-set look-ahead of the penalty contacts along a Newton step."""

from __future__ import annotations

import logging

import numpy as np

from eyefem.solve.linsolve import NegativeCurvature
from eyefem.solve.model import Model
from eyefem.solve.options import NewtonOptions
from eyefem.solve.records import StepResult, StepStatus

log = logging.getLogger(__name__)

LOOKAHEAD_DENSE_BYTES = 256 * 2**20
"""The look-ahead adds its nodes' penalty stiffness by a Woodbury update of the step's
factorisation while the update's dense columns (8 bytes x free dofs x nodes, three
arrays of them: the columns, their back-solves and the solver's copies) stay below this
size; above it the stiffness is added to the sparse tangent, which is factorised anew.
On the finer eye (48,324 hexahedra, 180,000 free dofs: 1.4 MB per node and array) the
flat tire's third tightening step took so many nodes into the look-ahead that the dense
columns grew the process by 18 GB, until the system killed it."""

UNSETTLED_REPAIRS = 3
"""A step whose state, converged with the contact pairs frozen, changes pairing for the
third time and leaves below contact_cycle_rtol x the load unbalanced is accepted
as on a contact cycle (NewtonOptions.contact_cycle_rtol)."""


def has_contact(model: Model) -> bool:
    """Whether the model has dynamic (re-paired) terms."""
    return any(t.dynamic for t in model.terms)


def settle_pairing(model: Model, q, theta, active, asm, opts: NewtonOptions, fref: float,
                   load: float, nf: float, it: int, flips: list, solver):
    """A state converged with the contact pairs frozen, re-paired at q (n_dof,).

    Returns (StepResult, None) when it stands: balanced re-paired (to contact_rtol), or a
    pairing that cycles or has not settled after UNSETTLED_REPAIRS re-pairings and leaves
    less than contact_cycle_rtol unbalanced (flagged CONTACT_CYCLE, at the pairing it is in
    equilibrium with). Else (None, (re-paired model, its residual (n_dof,), its free force
    residual)): Newton goes on from it; ``flips`` (the forces earlier re-pairings left)
    gets this one. ``load``: the force the state carries, N (the bounds are relative to
    it); ``fref``: the step's progress reference, passed on to the result."""
    free = asm.free_primal
    rep, r2, nf2, fc = repaired(model, q, theta, active, free)
    bound = max(load, fc)
    if nf2 <= opts.contact_rtol * bound + opts.atol:
        asm.model = rep
        return StepResult(rep, q, it, nf2, solver, fref, load_N=load), None
    cycles = any(abs(nf2 - f) <= 0.01 * nf2 for f in flips)
    if (cycles or len(flips) + 1 >= UNSETTLED_REPAIRS) and nf2 <= opts.contact_cycle_rtol * bound:
        log.warning("contact pairing %s at convergence (nodes %s flip between facets): accepted "
                    "with the pairing it is in equilibrium with; re-paired, %.3e N is left "
                    "unbalanced (%.1e of the load %.3e N)", "cycles" if cycles else
                    f"has not settled after {len(flips) + 1} re-pairings",
                    node_list(repaired_nodes(model, rep)), nf2, nf2 / bound, bound)
        return StepResult(model, q, it, nf, solver, fref, StepStatus.CONTACT_CYCLE, nf2,
                          load), None
    flips.append(nf2)
    if log.isEnabledFor(logging.DEBUG):
        node, f_node = largest_nodal_force(r2, free, model.mesh.n_nodes)
        log.debug("  converged with the pairs frozen; re-paired, %.3e N out of balance "
                  "(pairing changed at nodes %s; largest force %.3e N at node %d)",
                  nf2, node_list(repaired_nodes(model, rep)), f_node, node)
    return None, (rep, r2, nf2)


def repaired(model: Model, q, theta, active, free):
    """The model re-paired at q, its residual (n_dof,), free force residual and the free
    force of its contact (dynamic) terms, N."""
    repaired = model.update(q, theta)
    r = repaired.gradient(q, theta, active)
    dyn = [t.name for t in repaired.terms if t.dynamic and (active is None or t.name in active)]
    fc = np.linalg.norm(repaired.gradient(q, theta, dyn)[free]) if dyn else 0.0
    return repaired, r, np.linalg.norm(r[free]), fc


def repaired_nodes(old: Model, new: Model) -> np.ndarray:
    """Slave nodes whose contact pairing differs between two models of the same terms."""
    nodes = []
    for a, b in zip(old.terms, new.terms):
        if not a.dynamic:
            continue
        rows = []
        for t in (a, b):
            w = np.asarray(t.data.get("w", np.ones(len(t.dofs)))) > 0
            rows.append({tuple(r) for r in np.asarray(t.dofs)[w].tolist()})
        nodes += [r[0] // 3 for r in rows[0] ^ rows[1]]
    return np.unique(np.array(nodes, dtype=np.int64))


def largest_nodal_force(r, free, n_nodes):
    """(node, force N) of the largest unbalanced free nodal force in the residual r (n_dof,)."""
    f = np.zeros(3 * n_nodes)
    sel = free[free < 3 * n_nodes]
    f[sel] = r[sel]
    norms = np.linalg.norm(f.reshape(-1, 3), axis=1)
    return int(np.argmax(norms)), float(norms.max())


def node_list(nodes, at_most=8) -> str:
    more = f" and {len(nodes) - at_most} more" if len(nodes) > at_most else ""
    return ", ".join(str(n) for n in nodes[:at_most]) + more if len(nodes) else "none found"


def lookahead(model, asm, q, theta, active, solver, rf, rm, x, y, rounds=4, end_gap=False):
    """Active-set look-ahead of the penalty contacts along a Newton step (x, y).

    A smoothed penalty node more than 2 eps outside the surface has almost no stiffness
    in the tangent, so a step that pushes it in runs it deep into the penalty: the
    residual jumps and the line search crawls at 1/8 of the step (observed at the edge of
    the ridged tire, where the sclera bulges out against the tire's rounded edge). Such a
    node (gap g > 2 eps now, g + dg < -eps along the step) enters the system with the
    plain penalty's quadratic model 1/2 alpha (g + G . dq)^2 (force alpha g G, stiffness
    alpha G G^T) and the step is solved again; a node the new step keeps outside
    (g + dg > 0) leaves the set again (a primal-dual active-set update), for at most
    ``rounds`` solves. Each node's stiffness is a rank-one update alpha v v^T (v: G on
    the free dofs) of the step's factorised ``solver`` (Woodbury: no refactorisation;
    for more nodes than LOOKAHEAD_DENSE_BYTES allows, a new factorisation of the tangent
    with their stiffness added).
    With ``end_gap`` the exact gap at the step's end must be below -eps too, which keeps
    out nodes whose linearised gap is meaningless over the step: beyond the edges of an
    encircling buckle the gap grows with the cube of the distance from the edge, and a
    node millimetres away sliding along the sclera had a linearised gap change of -10^2
    to -10^3 mm; on default case 4 up to 762 such nodes entered the look-ahead in one
    iteration. The solver sets it with the Gauss-Newton contact tangent
    (``NewtonOptions.contact_curvature``): with the exact tangent those nodes' stiffness
    alpha |G|^2 happened to hold the soft sliding modes beside the tire, and without
    them default case 4 took more iterations (docs/performance.md, "The contact tangent without
    the buckle's curvature").
    Returns (x, y, solver of the last solve, number of look-ahead nodes)."""
    members = {}
    la_solver = None
    x0, y0 = x, y
    for _ in range(rounds):
        lin = model.gap_linearisations(q, asm.expand(x, y), theta, active)
        changed = False
        for t, g, dg, G, g_end in lin:
            eps = t.smoothing
            m = members.get(t.name, np.zeros(len(g), bool))
            enter = (g > 2 * eps) & (g + dg < -eps) & ((g_end < -eps) if end_gap else True)
            new = (m | enter) & ~(m & (g + dg > 0))
            changed |= bool(np.any(new != m))
            members[t.name] = new
        if not changed:
            break
        la_solver = None  # the last round's update freed before this round's is built
        gx = np.zeros(model.n_dof)
        n_nodes = sum(int(np.sum(m)) for m in members.values())
        sparse = 3 * 8.0 * len(asm.free_primal) * n_nodes > LOOKAHEAD_DENSE_BYTES
        terms, blocks = [], []
        for t, g, dg, G, _ in lin:
            m = np.nonzero(members[t.name])[0]
            a = t.data["alpha"][m]
            gx += np.bincount(t.dofs[m].ravel(), ((a * g[m])[:, None] * G[m]).ravel(),
                              minlength=model.n_dof)
            if sparse:  # alpha G G^T per node, on the free dofs
                blocks.append(asm.coo(t.dofs[m], a[:, None, None] * G[m][:, :, None]
                                      * G[m][:, None, :]))
                continue
            for i, al in zip(m, a):
                v = np.zeros(model.n_dof)
                v[t.dofs[i]] = G[i]
                terms.append((al, v[asm.free_primal]))
        if sparse:
            log.debug("  contact look-ahead: %d nodes, added to the tangent and factorised "
                      "anew", n_nodes)
            la_solver = solver.plus_sparse(sum(blocks[1:], blocks[0]))
        else:
            la_solver = solver.plus_low_rank(terms) if terms else solver
        try:
            x, y = la_solver.solve(-(rf + gx[asm.free_primal]), -rm)
        except NegativeCurvature:  # roundoff of the update on a nearly singular tangent
            log.debug("  contact look-ahead dropped: negative curvature")
            return x0, y0, solver, 0
    n = int(sum(np.sum(m) for m in members.values()))
    return x, y, la_solver, n

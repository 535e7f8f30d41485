"""Why a load path failed, in words: bodies that nothing holds (a singular tangent), a load
past the structure's limit point, material constants that differ by many orders.

Used by the load path (eyefem.solve.loadpath) when a step fails after all its cuts; each
function returns sentences to append to the error message ("" when it finds nothing).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from eyefem.solve.model import Model

MOTIONS = ("translate along x", "translate along y", "translate along z",
           "rotate about x", "rotate about y", "rotate about z")
"""The six rigid motions, in the order of :func:`rigid_modes`."""

FREE_MOTION_RTOL = 1e-7
"""A rigid motion m of a body is free when |K m| <= FREE_MOTION_RTOL |K d| for a
deformation d of the same size (the tangent does not resist it)."""

SOFTENING_RATIO = 5.0
"""The response softened this many times along a stage (displacement per load factor of
its last converged step against its first) is taken as a limit point ahead."""

STIFFNESS_SPREAD = 1e6
"""Shear moduli of the materials of one model further apart than this ratio are named."""


def rigid_modes(x: np.ndarray) -> np.ndarray:
    """The six rigid motions (6, n, 3) of points x (n, 3) (mm): unit translations along
    x, y, z and infinitesimal rotations about axes through the points' centroid."""
    c = x - x.mean(axis=0)
    modes = np.zeros((6,) + x.shape)
    for k in range(3):
        modes[k, :, k] = 1.0
        modes[3 + k] = np.cross(np.eye(3)[k], c)
    return modes


def bodies(model: Model, prescribed: np.ndarray, active=None) -> list[np.ndarray]:
    """Node ids of each group of nodes that the active terms tie together (n_i,), leaving
    out groups tied to unknowns other than displacements (a rigid body's dofs) and nodes
    whose three displacements are all prescribed."""
    n_nodes, n_u = model.mesh.n_nodes, model.n_u
    rows, cols = [], []
    extra = np.zeros(n_nodes, bool)
    mult = np.asarray(model.multiplier_dofs)
    for term in model._active(active):
        d = np.asarray(term.dofs)
        if d.size == 0:
            continue
        nodes = np.where(d < n_u, d // 3, -1)
        for j in range(1, d.shape[1]):
            ok = (nodes[:, 0] >= 0) & (nodes[:, j] >= 0)
            rows.append(nodes[ok, 0])
            cols.append(nodes[ok, j])
        # items that touch a non-multiplier extra dof tie their nodes to a body that is not
        # a mesh (a rigid buckle): those groups are left out
        beyond = (d >= n_u) & ~np.isin(d, mult)
        touched = np.where(beyond.any(axis=1)[:, None] & (nodes >= 0), nodes, -1)
        extra[touched[touched >= 0]] = True
        lone = nodes[:, 0][nodes[:, 0] >= 0]
        rows.append(lone)
        cols.append(lone)
    if not rows:
        return []
    r, c = np.concatenate(rows), np.concatenate(cols)
    used = np.zeros(n_nodes, bool)
    used[r] = True
    used[c] = True
    graph = sp.coo_matrix((np.ones(len(r)), (r, c)), shape=(n_nodes, n_nodes))
    _, labels = connected_components(graph, directed=False)
    held = prescribed[:n_u].reshape(n_nodes, 3).all(axis=1)
    out = []
    for lab in np.unique(labels[used]):
        ids = np.nonzero((labels == lab) & used & ~held)[0]
        if len(ids) and not extra[labels == lab].any():
            out.append(ids)
    return out


def free_motions(model: Model, q, theta, prescribed: np.ndarray, active=None) -> str:
    """Sentences naming the bodies the tangent at q does not hold, with their free rigid
    motions (a singular tangent); "" if every body is held. ``prescribed`` (n_dof,) bool."""
    n_nodes, n_u = model.mesh.n_nodes, model.n_u
    x = model.mesh.nodes + np.asarray(q[:n_u]).reshape(n_nodes, 3)
    rng = np.random.default_rng(0)
    found = []
    for ids in bodies(model, prescribed, active):
        dofs = (3 * ids[:, None] + np.arange(3)).ravel()
        d = np.zeros(model.n_dof)
        d[dofs] = rng.standard_normal(len(dofs))
        d[prescribed] = 0.0
        scale = np.linalg.norm(model.hvp(q, d, theta, active)) / max(np.linalg.norm(d), 1e-300)
        free = []
        for k, mode in enumerate(rigid_modes(x[ids])):
            m = np.zeros(model.n_dof)
            m[dofs] = mode.ravel()
            if np.any(m[prescribed] != 0.0) or not np.any(m):
                continue
            km = np.linalg.norm(model.hvp(q, m, theta, active)) / np.linalg.norm(m)
            if km <= FREE_MOTION_RTOL * scale:
                free.append(MOTIONS[k])
        if free:
            found.append(f"{_describe(model, ids, active)} can {_join(free)} freely (nothing "
                         "holds it: no prescribed displacement, spring, contact or suture "
                         "resists that motion, so the tangent is singular)")
    if not found:
        return ""
    return ("; ".join(found).capitalize() + ". Prescribe a displacement (or add a spring) "
            "that stops each free motion.")


def limit_point(steps: list[tuple[float, np.ndarray]], stage) -> str:
    """A sentence if the response softened along a stage that ramps a load (its params):
    ``steps`` are (load factor, state (n_dof,)) of its start and converged steps."""
    if not stage.params or len(steps) < 3:
        return ""
    rates = [np.linalg.norm(q1 - q0) / (t1 - t0)
             for (t0, q0), (t1, q1) in zip(steps[:-1], steps[1:]) if t1 > t0]
    if len(rates) < 2 or rates[0] <= 0 or rates[-1] < SOFTENING_RATIO * rates[0]:
        return ""
    loads = ", ".join(f"{name}.{key}" for name, p in stage.params.items() for key in p)
    t = steps[-1][0]
    return (f"The response softened {rates[-1] / rates[0]:.0f}-fold along stage '{stage.name}' "
            f"(displacement per load increment, last step against the first): the load "
            f"({loads}) is at the structure's limit point near t = {t:.4g}, the largest load "
            f"it carries, past which no equilibrium exists under load control. Stop the load "
            f"below it, or prescribe the volume instead of the pressure (volume control: a "
            f"closed cavity with an injected volume passes a limit point).")


def stiffness_spread(model: Model, theta) -> str:
    """A sentence if the materials' initial shear moduli differ by more than
    STIFFNESS_SPREAD (a singular or badly conditioned tangent); "" otherwise."""
    for term in model.terms:
        p = theta.get(term.name) if isinstance(theta, dict) else None
        if not isinstance(p, dict) or "coeffs" not in p or not hasattr(term, "mesh"):
            continue
        c = np.asarray(p["coeffs"])
        mu = 2.0 * (c[:, 1, 0] + c[:, 0, 1])
        names = term.mesh.materials
        if len(mu) > 1 and mu.min() > 0 and mu.max() > STIFFNESS_SPREAD * mu.min():
            lo, hi = int(np.argmin(mu)), int(np.argmax(mu))
            return (f"The materials' shear moduli differ by {mu.max() / mu.min():.1e}: "
                    f"'{names[lo]}' {mu[lo]:.3g} MPa against '{names[hi]}' {mu[hi]:.3g} MPa; "
                    "a unit slip (kPa for MPa)?")
    return ""


def _describe(model: Model, ids: np.ndarray, active) -> str:
    """'the body of N nodes (materials ..., terms ...)'."""
    mesh = model.mesh
    in_body = np.zeros(mesh.n_nodes, bool)
    in_body[ids] = True
    elems = np.nonzero(in_body[mesh.hexes].any(axis=1))[0]
    mats = sorted({mesh.materials[m] for m in np.unique(mesh.material_ids[elems])})
    n_u = model.n_u
    terms = [t.name for t in model._active(active)
             if np.asarray(t.dofs).size and in_body[np.asarray(t.dofs)[np.asarray(t.dofs) < n_u]
                                                      // 3].any()]
    what = f"materials {', '.join(repr(m) for m in mats)}; " if mats else ""
    return f"the body of {len(ids)} nodes ({what}terms {', '.join(repr(t) for t in terms)})"


def _join(words: list[str]) -> str:
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]

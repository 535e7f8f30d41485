"""Tangent verification: autodiff vs hand-coded vs finite differences, for every energy term.

A check is a function ``fn(rng) -> CheckData`` listed by name in :func:`term_checks`;
it builds a random deformed state of one term and returns the
autodiff residual and tangent, the hand-coded ones, and the autodiff residual as a
function (for central finite differences). ``eyefem verify-tangents`` prints the table.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.bars import Bars, TiedBars, bilinear, end_patches, patch_weights
from eyefem.fem.loop_solid import ShortenedLoopSolid
from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.mesh import HEX_CORNERS, HEX_FACES, Mesh
from eyefem.fem.solid import SolidQ1P0
from eyefem.fem.solid_im import SolidQ1P0IM
from eyefem.fem.surface import face_cone_volume
from eyefem.fem.terms import OrbitSpring
from eyefem.verify.cavity_handcoded import cavity_check
from eyefem.verify.checks import (
    FD_TOL,
    HAND_TOL,
    CheckData,
    TangentCheck,
    fd_tangent,
    random_deformation,
    relative_difference,
)
from eyefem.verify.contact_handcoded import contact_checks
from eyefem.verify.handcoded import (
    bar_residual_tangent,
    pressure_face_residual_tangent,
    q1p0_residual_tangent,
    smoothed_bar_residual_tangent,
)


_COMPILED: dict = {}


def _compiled(term, kind: str):
    """A term's local kernel ``kind`` ("grad_hess"; for the element energy "grad",
    "hessian"), compiled once per term class and static configuration and shared by the
    checks of every seed: the kernels read arrays only from their arguments (as
    eyefem.solve.model.Model._kernel relies on), so the first term serves the later ones."""
    key = (type(term), term.static_key(), kind)
    if key not in _COMPILED:
        def energy(y, params, data):
            return term.local_energy(y[None], params, data)[0]
        _COMPILED[key] = jax.jit({"grad_hess": term.local_grad_hess, "grad": jax.grad(energy),
                                  "hessian": jax.hessian(energy)}[kind])
    return _COMPILED[key]


def _element_state(rng, X, term, params):
    """A random deformed state of one solid element with reference nodes X (8, 3): F, u
    (8, 3), lambda, the local dofs x (25,), the kernel's gradient g (1, 25) and Hessian H
    (1, 25, 25) there, and the kernel's residual as a function of x (for differences)."""
    F = random_deformation(rng)
    u = X @ F.T - X + 0.03 * rng.standard_normal((8, 3))
    lam = float(rng.uniform(-1, 1))
    x = np.concatenate([u.ravel(), [lam]])
    kern = _compiled(term, "grad_hess")

    def r_fun(y):
        return np.asarray(kern(jnp.asarray(y)[None], params, term.data)[0][0])

    g, H = kern(jnp.asarray(x)[None], params, term.data)
    return F, u, lam, x, g, H, r_fun


def _solid_check(terms, loop=False):
    """One Q1P0 element; ``loop``: off the z axis, in a loop shortened by a random length
    (:class:`eyefem.fem.loop_solid.ShortenedLoopSolid`), the hand-coded element evaluated at
    the loop's reference X - shortening e_rho / (2 pi) with u + shortening e_rho / (2 pi)."""
    def check(rng):
        X = HEX_CORNERS * 0.5 + 0.08 * rng.standard_normal((8, 3))
        X += [6.0, 1.0, 0.0] if loop else 0.0
        c = MooneyRivlin.from_terms("m", terms).coeffs
        mesh = Mesh(X, np.arange(8)[None], [0])
        if loop:
            term = ShortenedLoopSolid("solid", mesh, c[None], 24, loop_nodes=np.arange(8))
            s = float(rng.uniform(2.0, 6.0))
            params = {**term.params, "shortening": s}
        else:
            term, s = SolidQ1P0("solid", mesh, c[None], 24), 0.0
            params = term.params
        F, u, lam, x, g, H, r_fun = _element_state(rng, X, term, params)
        shift = s / (2 * np.pi) * np.column_stack([X[:, :2], np.zeros(8)]) \
            / np.hypot(X[:, 0], X[:, 1])[:, None]
        r, K = q1p0_residual_tangent(X - shift, u + shift, lam, c)
        return CheckData(np.asarray(g[0]), r, np.asarray(H[0]), K, r_fun, x,
                         f"det F = {np.linalg.det(F):.3f}, lambda = {lam:.3f} MPa"
                         + (f", shortening {s:.2f} mm" if loop else ""))
    return check


def _incompatible_modes_check(rng):
    """One Q1P0 element with incompatible modes (:class:`eyefem.fem.solid_im.SolidQ1P0IM`).
    It has no hand-coded form: its kernel's explicit condensation (g_u - K_ua K_aa^-1 g_a,
    K_uu - K_ua K_aa^-1 K_au at alpha*) is checked against the straight autodiff gradient
    and Hessian of the condensed energy (through the inner Newton iterations on alpha) in
    the 'hand' columns, and against central differences of its residual."""
    X = HEX_CORNERS * np.array([1.0, 0.6, 0.25]) + 0.03 * rng.standard_normal((8, 3))
    c = MooneyRivlin.from_terms("m", {"c10": 0.5, "c01": 0.2, "c20": 0.1}).coeffs
    term = SolidQ1P0IM("solid", Mesh(X, np.arange(8)[None], [0]), c[None], 24)
    F, _, lam, x, g, H, r_fun = _element_state(rng, X, term, term.params)
    r = np.asarray(_compiled(term, "grad")(jnp.asarray(x), term.params, term.data))
    K = np.array(_compiled(term, "hessian")(jnp.asarray(x), term.params, term.data))
    return CheckData(np.asarray(g[0]), r, np.asarray(H[0]), K, r_fun, x,
                     f"det F = {np.linalg.det(F):.3f}, lambda = {lam:.3f} MPa, a 2 x 1.2 x 0.5 "
                     "mm brick")


def _pressure_check(rng):
    """Follower pressure assembled over the closed boundary of a deformed hexahedron."""
    X = HEX_CORNERS * 0.5
    F = random_deformation(rng, 0.3)
    x = (X @ F.T + 0.05 * rng.standard_normal((8, 3))).ravel()
    faces = HEX_FACES
    p = float(rng.uniform(0.1, 1.0))

    def energy(y):
        return p * jnp.sum(face_cone_volume(y.reshape(8, 3)[faces], jnp.zeros(3)))

    grad = jax.jit(jax.grad(energy))
    H = np.asarray(jax.hessian(energy)(jnp.asarray(x)))
    r = np.zeros(24)
    K = np.zeros((24, 24))
    for f in faces:
        rf, kf = pressure_face_residual_tangent(x.reshape(8, 3)[f], p)
        d = (3 * f[:, None] + np.arange(3)).ravel()
        r[d] += rf
        K[np.ix_(d, d)] += kf
    return CheckData(np.asarray(grad(jnp.asarray(x))), r, H, K,
                     lambda y: np.asarray(grad(jnp.asarray(y))), x, f"p = {p:.3f} MPa")


def _bar_check(rng):
    """A suture bar from a point inside a distorted face to a node, tightened by 5%."""
    X = np.array([[0, 0, 0], [1, 0, 0], [1.1, 1, 0.2], [0, 0.9, 0], [0.4, 0.3, 2.0]])
    bar = Bars("bar", [[0, 1, 2, 3]], [[4] * 4], [rng.uniform(-0.8, 0.8, 2)], [[0, 0]], X,
               EA=3.0)
    p = {**bar.params, "shortening": np.array([0.05])}
    u = 0.2 * rng.standard_normal((5, 3))
    x = u[bar.dofs[0, ::3] // 3].ravel()
    kern = jax.jit(bar.local_grad_hess)
    g, H = kern(jnp.asarray(x)[None], p, bar.data)
    T = np.zeros((6, 24))
    T[:3, :12] = np.kron(bilinear(p["xi"][0, 0])[None], np.eye(3))
    T[3:, 12:] = np.kron(bilinear(p["xi"][0, 1])[None], np.eye(3))
    xs = bar.data["X"][0].ravel() + x
    L0 = bar.data["L0"][0]
    f, k = bar_residual_tangent(T[:3] @ xs, T[3:] @ xs, 3.0, L0, 0.95 * L0)
    return CheckData(np.asarray(g[0]), T.T @ f, np.asarray(H[0]), T.T @ k @ T,
                     lambda y: np.asarray(kern(jnp.asarray(y)[None], p, bar.data)[0][0]), x,
                     "embedded end, shortening 5%")


def _tied_check(bar, x, wa, wb, state):
    """CheckData of a one-bar TiedBars at local dofs x, tightened to 0.5 smoothing lengths
    of stretch; hand-coded: the smoothed bar mapped by the ends' node weights wa (m_a,) and
    wb (m_b,) (x_end = sum_j w_j x_j)."""
    L = float(bar.lengths(jnp.asarray(x)[None], bar.params, bar.data)[0])
    p = {**bar.params, "tightening": np.array([bar.params["L0"][0] - L + 0.005])}
    kern = jax.jit(bar.local_grad_hess)
    g, H = kern(jnp.asarray(x)[None], p, bar.data)
    ma = len(wa)
    T = np.zeros((6, 3 * (ma + len(wb))))
    T[:3, :3 * ma] = np.kron(np.asarray(wa)[None], np.eye(3))
    T[3:, 3 * ma:] = np.kron(np.asarray(wb)[None], np.eye(3))
    xs = bar.data["X"][0].ravel() + x
    L0 = bar.params["L0"][0]
    f, k = smoothed_bar_residual_tangent(T[:3] @ xs, T[3:] @ xs, 3.0, L0, L0 - p["tightening"][0],
                                         0.01)
    return CheckData(np.asarray(g[0]), T.T @ f, np.asarray(H[0]), T.T @ k @ T,
                     lambda y: np.asarray(kern(jnp.asarray(y)[None], p, bar.data)[0][0]), x, state)


def _tied_bar_check(rng):
    """A tension-only suture bar between points inside two distorted faces (a bite in the
    sclera, a point on a deformable buckle), tied and shortened to within a few smoothing
    lengths of slack, so that the smoothed stretch is exercised."""
    X = np.array([[0, 0, 0], [1, 0, 0], [1.1, 1, 0.2], [0, 0.9, 0],
                  [0.2, 0.1, 2.0], [1.2, 0.0, 2.1], [1.0, 1.1, 1.9], [0.1, 1.0, 2.0]])
    xi = rng.uniform(-0.8, 0.8, (2, 2))
    bar = TiedBars("tied", [[0, 1, 2, 3]], [[4, 5, 6, 7]], xi[:1], xi[1:], X, EA=3.0, smoothing=0.01)
    x = 0.02 * rng.standard_normal(24)
    return _tied_check(bar, x, bilinear(xi[0]), bilinear(xi[1]), "face to face, 0.5 eps of stretch")


def _spread_bite_check(rng, elliptic=False):
    """A tied suture bar whose bite is spread over a patch (a disc of radius 1 mm, or with
    ``elliptic`` an ellipse 0.4 mm across and 1.2 mm along the tangent normal to the bar)
    of a curved 6 x 6 grid of faces (a cap of a 12 mm sphere) to a point in a face above
    it. Hand-coded: the smoothed bar mapped by the patch weights (x_a = sum_j w_j x_j)."""
    n, half = 6, 1.5
    g = np.linspace(-half, half, n + 1)
    P = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    d = np.column_stack([P, np.full(len(P), 12.0)])
    X = 12.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    X = np.vstack([X, [[0.2, 0.1, 14.0], [1.2, 0.0, 14.1], [1.0, 1.1, 13.9], [0.1, 1.0, 14.0]]])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    F = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    f4, top = F[[14]], [[49, 50, 51, 52]]
    xi = rng.uniform(-0.8, 0.8, (2, 2))
    patch = (end_patches(X, F, f4, xi[:1], True, 0.4, half_length=1.2,
                         toward=X[top].mean(1) + [[2.0, 0.0, 0.0]]) if elliptic else
             end_patches(X, F, f4, xi[:1], True, 1.0))
    bar = TiedBars("tied", f4, top, xi[:1], xi[1:], X, EA=3.0, smoothing=0.01, patch_a=patch)
    x = (0.02 * rng.standard_normal(X.shape))[bar.dofs[0, ::3] // 3].ravel()
    w = np.asarray(patch_weights(jnp.asarray(X[patch.nodes]), jnp.asarray(xi[:1]), patch.data()))
    return _tied_check(bar, x, w[0], bilinear(xi[1]),
                       f"bite over {patch.nodes.shape[1]} nodes, 0.5 eps of stretch")


def _orbit_check(rng, tilted=False):
    """The orbit springs on a perturbed ring of 12 nodes, displaced at random. Hand-coded:
    each rigid mode's unit-amplitude field (a rotation about an axis through the
    centroid, a shift along an axis) projected by least squares, r = sum k_a m_a (m_a . u).
    ``tilted``: the lateral shifts along two random orthonormal directions (``shift_axes``),
    the axial one along their normal."""
    phi = 2 * np.pi * np.arange(12) / 12
    X = np.stack([11 * np.cos(phi), 11 * np.sin(phi), np.zeros(12)], 1) + 0.3 * rng.standard_normal((12, 3))
    k = np.array([5.0, 6.0, 7.0, 0.8, 0.8, 0.3])
    axes = np.linalg.qr(rng.standard_normal((3, 3)))[0].T if tilted else np.eye(3)
    term = OrbitSpring("orbit", np.arange(12), X, k_rot=tuple(k[:3]), k_trans=0.8, k_axial=0.3,
                       shift_axes=tuple(map(tuple, axes[:2])) if tilted else None)
    u = 0.05 * rng.standard_normal(36)
    kern = jax.jit(term.local_grad_hess)
    g, H = kern(jnp.asarray(u)[None], term.params, term.data)
    c = X.mean(axis=0)
    fields = [np.cross(np.eye(3)[a], X - c).ravel() for a in range(3)]
    fields += [np.tile(axes[a], 12) for a in range(3)]
    A = np.stack(fields, 1)  # (36, 6): u ~ A m, least squares m = (A^T A)^-1 A^T u
    M = np.linalg.solve(A[:, :3].T @ A[:, :3], A[:, :3].T)  # rotations fitted about c
    M = np.vstack([M, A[:, 3:].T / 12])  # shifts: mean displacement
    K_hand = M.T @ np.diag(k) @ M
    return CheckData(np.asarray(g[0]), K_hand @ u, np.asarray(H[0]), K_hand,
                     lambda y: np.asarray(kern(jnp.asarray(y)[None], term.params, term.data)[0][0]),
                     u, "perturbed ring, random displacement")




def term_checks() -> dict[str, Callable[[np.random.Generator], CheckData]]:
    """Every term's tangent check, by name, in the order ``eyefem verify-tangents`` prints."""
    return {
        "solid_q1p0_neo_hookean": _solid_check({"c10": 0.0833}),
        "solid_q1p0_mooney_rivlin": _solid_check({"c10": 25.0, "c01": 5.0}),
        "solid_q1p0_generalised": _solid_check(
            {"c10": 0.5, "c01": 0.2, "c20": 0.1, "c11": 0.05, "c02": 0.02, "c30": 0.01, "c03": 0.005}),
        "solid_q1p0_shortened_loop": _solid_check({"c10": 1.0, "c01": 0.1}, loop=True),
        "solid_q1p0_incompatible_modes": _incompatible_modes_check,
        "follower_pressure": _pressure_check,
        "orbit_spring": _orbit_check,
        "orbit_spring_tilted_shift": lambda rng: _orbit_check(rng, tilted=True),
        "suture_bar": _bar_check,
        "tied_suture_bar": _tied_bar_check,
        "tied_suture_bar_spread_bite": _spread_bite_check,
        "tied_suture_bar_elliptic_bite": lambda rng: _spread_bite_check(rng, elliptic=True),
        "fluid_cavity": cavity_check,
        **contact_checks(),
    }


def verify_tangents(seed: int = 0, terms=None) -> list[TangentCheck]:
    """Run the checks of :func:`term_checks` (or the named ones) at random states."""
    jax.config.update("jax_enable_x64", True)
    assert jnp.zeros(1).dtype == jnp.float64
    out = []
    for name, fn in term_checks().items():
        if terms is not None and name not in terms:
            continue
        d = fn(np.random.default_rng(seed))
        K_fd = fd_tangent(d.r_fun, d.x)
        out.append(TangentCheck(name, relative_difference(d.r_ad, d.r_hand),
                                relative_difference(d.K_ad, d.K_hand),
                                relative_difference(d.K_ad, K_fd), d.state))
    return out


def format_table(checks: list[TangentCheck]) -> str:
    """Fixed-width table of the checks."""
    head = (f"{'term':<28} {'|dr|/|r| AD-hand':>17} {'|dK|/|K| AD-hand':>17} "
            f"{'|dK|/|K| AD-FD':>15}  result  state")
    lines = [head, "-" * len(head)]
    for c in checks:
        lines.append(f"{c.name:<28} {c.r_hand:>17.2e} {c.K_hand:>17.2e} {c.K_fd:>15.2e}  "
                     f"{'pass' if c.passed else 'FAIL':<6}  {c.state}")
    lines.append(f"(pass: AD vs hand-coded <= {HAND_TOL:g}, AD vs central FD <= {FD_TOL:g})")
    return "\n".join(lines)

"""Volume regulation of a closed cavity over time (eyefem.fem.regulation, issue 74): the
condensed law against its closed forms and the seed's law, the term's residual and tangent
against hand-coded and finite-difference ones, invariance under rigid motions, the
backward-Euler pressure decay of rigid-walled cavities against the closed-form recursion
and the ODE, the volume balance at every step, and the stages' time axis."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import expi

from eyefem.fem import generators
from eyefem.fem.cavity import FluidCavity, closing_hook
from eyefem.fem.materials import neo_hookean
from eyefem.fem.mesh import HEX_CORNERS, HEX_FACES, Mesh, boundary_faces
from eyefem.fem.regulation import (AQUEOUS, CHOROID_ESTIMATE, UL_MIN_MMHG, Regulation,
                                   condensed_pressure, regulated_state, step_times)
from eyefem.fem.surface import PressureLoad, face_cone_volume
from eyefem.fem.units import MMHG
from eyefem.problems.verification import shell_rigid_constraints
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage, solve
from eyefem.verify.cavity_handcoded import cavity_residual_tangent
from eyefem.verify.checks import random_deformation


# --- the law by hand (numpy, independent of the term's JAX code) ---------------------------

def _blood(x, emax, pb):
    return np.sign(x) * emax * (1.0 - np.exp(-abs(x) / pb))


def _blood_slope(x, emax, pb):
    return emax / pb * np.exp(-abs(x) / pb)


def _hand_pressure(V, p):
    """P of the regulated law at volume V: the root of the step's balance
    V = W - V_ini x / K - (C_out + dt C) x - E(x), x = P - P_ini (brentq, to roundoff);
    and -dP/dV."""
    dt, C = p["dt"], p["facility"]
    W = (p["v_ini"] + p["dv"] - p["paracentesis"] - p["drainage"] + p["aq_produced"]
         + dt * p["production"] - p["aq_outflow"] - dt * C * (p["p_ini"] - p["p_ev"]))
    s = p["v_ini"] / p["bulk"] + p["c_out"] + dt * C

    def g(x):
        return W - s * x - _blood(x, p["blood_max"], p["blood_scale"]) - V

    x = brentq(g, -1.0, 1.0, xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500)
    return p["p_ini"] + x, 1.0 / (s + _blood_slope(x, p["blood_max"], p["blood_scale"]))


def _regulated_params(term, **kw):
    return {**term.params, **{k: float(v) for k, v in kw.items()}}


def _deformed_hex(rng):
    """A cavity bounded by the faces of one deformed hexahedron (liquid inside): the mesh,
    the displacement u (24,) and the deformed volume (mm^3)."""
    X = HEX_CORNERS * 0.5
    x = (X @ random_deformation(rng, 0.3).T + 0.05 * rng.standard_normal((8, 3))).ravel()
    faces = HEX_FACES[:, ::-1]
    mesh = Mesh(X, np.arange(8)[None], [0], face_sets={"c": faces})
    v_def = -float(np.sum(face_cone_volume(jnp.asarray(x.reshape(8, 3)[faces]), jnp.zeros(3))))
    return mesh, x - X.ravel(), v_def


def _hex_term(rng):
    """A regulated cavity on a deformed hexahedron with every part of the law active:
    liquid, reservoir, a step's production and outflow, blood, injection, paracentesis,
    drainage and a history; the pressure ends some 20 mmHg above P_ini (x far from 0)."""
    mesh, u, v = _deformed_hex(rng)
    term = FluidCavity("cav", mesh, "c", p_ini=0.002, bulk=2.0, v_ini=1.005 * v,
                       outflow_compliance=0.05, regulation=Regulation(
                           facility=0.4, p_ev=0.0008, production=0.004, blood_max=0.004,
                           blood_scale=0.0025))
    p = _regulated_params(term, dt=0.3, dv=0.0016 * v, paracentesis=0.002 * v,
                          drainage=0.001 * v, aq_produced=0.003 * v, aq_outflow=0.004 * v,
                          time=12.0)
    return term, mesh, u, p


# --- the law ------------------------------------------------------------------------------

def test_without_regulation_the_law_is_the_seeds():
    """Zero regulation (no step duration, no blood) gives the seed's pressure, energy and
    -dP/dV = K_eff / V_ini to roundoff, with and without the reservoir C_out, and
    P = P_ini for a pressure-controlled liquid (K = 0)."""
    rng = np.random.default_rng(0)
    mesh, u, v = _deformed_hex(rng)
    for c_out, bulk in ((0.0, 2.0), (0.3, 2.0), (0.3, 0.0)):
        out = []
        for reg in (None, AQUEOUS):
            term = FluidCavity("c", mesh, "c", p_ini=0.002, bulk=bulk, v_ini=1.01 * v,
                               outflow_compliance=c_out, regulation=reg)
            p = {**term.params, "dv": 0.004 * v}
            E = float(term.energy(jnp.asarray(u), p, term.data, term.dofs))
            lr = term.low_rank(u, p, term.data, term.dofs)
            out.append((float(term.pressures(u, p)[0][0]), E, lr[0][0] if lr else 0.0))
        (Ps, Es, As), (Pr, Er, Ar) = out
        assert Pr == pytest.approx(Ps, rel=1e-13)
        assert Er == pytest.approx(Es, rel=1e-12)
        assert Ar == pytest.approx(As, rel=1e-13)
        assert (Pr == 0.002) == (bulk == 0.0)


def test_condensed_pressure_solves_the_step_balance():
    """Without blood the pressure is the closed form P_ini + a (W - V) / (1 + a (C_out +
    dt C)); with blood it is the root of the balance to roundoff (brentq on the law written
    out by hand), at pressures far above and below P_ini (blood expelled and taken up)."""
    rng = np.random.default_rng(1)
    term, mesh, u, p = _hex_term(rng)
    V = float(term.pressures(u, p)[1][0])
    a = p["bulk"] / p["v_ini"]
    W = (p["v_ini"] + p["dv"] - p["paracentesis"] - p["drainage"] + p["aq_produced"]
         + p["dt"] * p["production"] - p["aq_outflow"] - p["dt"] * p["facility"]
         * (p["p_ini"] - p["p_ev"]))
    lin = {**p, "blood_max": 0.0}
    closed = p["p_ini"] + a * (W - V) / (1 + a * (p["c_out"] + p["dt"] * p["facility"]))
    assert float(term.pressures(u, lin)[0][0]) == pytest.approx(closed, rel=1e-14)
    for dv in (0.004, -0.006):  # x about +39 and -25 mmHg
        q = {**p, "dv": dv * V}
        P, _ = term.pressures(u, q)
        P_hand, _ = _hand_pressure(V, q)
        assert abs(P[0] - q["p_ini"]) > 10 * MMHG
        assert P[0] == pytest.approx(P_hand, rel=1e-13)


def test_condensed_pressure_derivatives_against_central_differences():
    """The implicit first and second derivatives of the condensed pressure (its JVP rule,
    differentiated again) in all five arguments against central differences (relative
    step 1e-6): first derivatives to 1e-9, second to 1e-8 of their largest (measured 9e-11 and
    1.5e-10: the differences' truncation and roundoff)."""
    z0 = np.array([0.227, -0.051, 1.3, 1.1, 80.0, 50.0, 0.004, 0.002, 0.0025, 0.003])

    def F(z):  # two cavities: x about 1.2 p_b above and 0.7 p_b below P_ini
        return condensed_pressure(*(z[2 * i:2 * i + 2] for i in range(5)))

    J = np.asarray(jax.jacfwd(F)(jnp.asarray(z0)))
    H = np.asarray(jax.hessian(F)(jnp.asarray(z0)))  # (2, 10, 10)
    jac = jax.jit(jax.jacfwd(F))
    for i in range(10):
        h = 1e-6 * abs(z0[i])
        e = np.eye(10)[i] * h
        fd = (np.asarray(F(jnp.asarray(z0 + e))) - np.asarray(F(jnp.asarray(z0 - e)))) / (2 * h)
        fd2 = (np.asarray(jac(jnp.asarray(z0 + e))) - np.asarray(jac(jnp.asarray(z0 - e)))) / (2 * h)
        for k in range(2):
            assert np.abs(J[k, i] - fd[k]) <= 1e-9 * np.abs(J[k]).max()
            assert np.abs(H[k, :, i] - fd2[k]).max() <= 1e-8 * np.abs(H[k]).max()


# --- the term: residual, tangent, invariance -------------------------------------------------

def test_residual_and_tangent_against_hand_coded_and_finite_differences():
    """The regulated term's autodiff residual and tangent (face blocks + rank one) against
    the hand-coded follower load -P g, -P H + alpha g g^T with P and alpha = -dP/dV from
    the law solved by hand (eyefem.verify.cavity_handcoded for g and H), against the
    autodiff Hessian of the energy and against central differences of the residual; and
    the residual's derivative in the facility (what the adjoint contracts) against central
    differences."""
    rng = np.random.default_rng(2)
    term, mesh, u, p = _hex_term(rng)
    E = jax.jit(lambda y, pp: term.energy(y, pp, term.data, term.dofs))
    grad = jax.jit(jax.grad(E))
    r_ad = np.asarray(grad(jnp.asarray(u), p))
    gl, Hl = term.grad_hess(jnp.asarray(u), p, term.data, term.dofs)
    K_ad = np.zeros((24, 24))
    np.add.at(K_ad, (term.dofs[:, :, None], term.dofs[:, None, :]), np.asarray(Hl))
    r_blocks = np.bincount(term.dofs.ravel(), np.asarray(gl).ravel(), minlength=24)
    (al, w), = term.low_rank(u, p, term.data, term.dofs)
    K_ad += al * np.outer(w, w)
    x = mesh.nodes + u.reshape(8, 3)
    V = float(term.pressures(u, p)[1][0])
    P, alpha = _hand_pressure(V, p)
    r_h, K_h, _, _ = cavity_residual_tangent(x, mesh.face_set("c"), P, 1.0, 0.0)
    g_h = -r_h / P
    K_h = K_h + alpha * np.outer(g_h, g_h)
    scale = np.abs(K_h).max()
    assert 10 < (P - p["p_ini"]) / MMHG < 30  # some 20 mmHg above P_ini: blood expelled
    np.testing.assert_allclose(r_ad, r_h, rtol=0, atol=1e-12 * np.abs(r_h).max())
    np.testing.assert_allclose(r_blocks, r_h, rtol=0, atol=1e-12 * np.abs(r_h).max())
    np.testing.assert_allclose(K_ad, K_h, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(K_ad, np.asarray(jax.hessian(E)(jnp.asarray(u), p)), rtol=0,
                               atol=1e-10 * scale)
    h = 1e-6
    fd = np.stack([(np.asarray(grad(jnp.asarray(u + h * e), p))
                    - np.asarray(grad(jnp.asarray(u - h * e), p))) / (2 * h) for e in np.eye(24)])
    np.testing.assert_allclose(K_ad, fd, rtol=0, atol=1e-7 * scale)
    dr = jax.jacfwd(lambda c: grad(jnp.asarray(u), {**p, "facility": c}))(p["facility"])
    hc = 1e-6 * p["facility"]
    fd = (np.asarray(grad(jnp.asarray(u), {**p, "facility": p["facility"] + hc}))
          - np.asarray(grad(jnp.asarray(u), {**p, "facility": p["facility"] - hc}))) / (2 * hc)
    np.testing.assert_allclose(np.asarray(dr), fd, rtol=0, atol=1e-7 * np.abs(fd).max())


def test_rigid_motions_change_neither_pressure_nor_energy_nor_balance():
    """A rotation and translation of the deformed cavity leave its pressure, energy and
    every volume of the report unchanged (1e-12) and rotate the residual."""
    rng = np.random.default_rng(3)
    term, mesh, u, p = _hex_term(rng)
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    x = mesh.nodes + u.reshape(8, 3)
    u2 = (x @ Q.T + np.array([1.0, -2.0, 0.5]) - mesh.nodes).ravel()
    grad = jax.grad(lambda y: term.energy(y, p, term.data, term.dofs))
    E1 = float(term.energy(jnp.asarray(u), p, term.data, term.dofs))
    E2 = float(term.energy(jnp.asarray(u2), p, term.data, term.dofs))
    assert E2 == pytest.approx(E1, rel=1e-12)
    r1, r2 = (np.asarray(grad(jnp.asarray(v))).reshape(8, 3) for v in (u, u2))
    np.testing.assert_allclose(r2, r1 @ Q.T, rtol=0, atol=1e-12 * np.abs(r1).max())
    a, b = term.report(u, p), term.report(u2, p)
    for k in a:
        if k != "balance_mm3":
            assert b[k] == pytest.approx(a[k], rel=1e-12, abs=1e-15), k
    assert abs(a["balance_mm3"]) < 1e-14 and abs(b["balance_mm3"]) < 1e-14


# --- rigid-walled cavities over time --------------------------------------------------------

def hollow_box(h=2.0):
    """A 3x3x3 block of cubes (edge h) without its centre cube: a cavity of volume h^3."""
    m = generators.box(3 * h, 3 * h, 3 * h, 3, 3, 3)
    keep = np.array([e for e in range(27) if e != 13])
    hexes = m.hexes[keep]
    hole = set(m.hexes[13].tolist())
    bf = boundary_faces(hexes)
    inner = bf[[set(f.tolist()) <= hole for f in bf]]
    outer = np.unique(bf[[not set(f.tolist()) <= hole for f in bf]])
    return Mesh(m.nodes, hexes, np.zeros(26, int), ("wall",), {"outer": outer},
                {"cavity": inner})


def _rigid_box_history(regulation, bulk, dv, times):
    """The hollow box, its outer surface held: its wall is incompressible (Q1P0), so the
    cavity keeps its volume exactly (a rigid wall). dV injected at once (no duration),
    then relaxation to ``times`` (min). Returns V_ini and rows (time, P, V) per step."""
    m = hollow_box()
    cav = FluidCavity("cav", m, "cavity", p_ini=10 * MMHG, bulk=bulk, regulation=regulation)
    model = solid_model(m, {"wall": neo_hookean("wall", 0.1)}, (cav,))
    d = node_dofs(m.node_set("outer"))
    fix = (d, np.zeros(len(d)))
    rows = []

    def on_step(rec, model, q, theta):
        r = model.report(q, theta)
        rows.append((r["cav/time_min"], r["cav/pressure_MPa"], r["cav/volume_mm3"]))

    solve(model, [Stage("inject", 1, fix, params={"cav": {"dv": dv}}),
                  Stage("relax", len(times), fix, times=times)], on_step=on_step)
    return cav.params["v_ini"], rows


def test_rigid_walled_cavity_decays_as_the_backward_euler_recursion_and_the_ode():
    """Rigid wall, liquid of bulk modulus K (compliance s = V_ini / K), Goldmann outflow:
    backward Euler gives P_n - P_ss = (P_{n-1} - P_ss) / (1 + C dt_n / s), P_ss = P_ev +
    F / C, which the model follows to 1e-12 over steps of 0.05 to 0.8 tau (tau = s / C).
    The recursion converges at first order to the ODE's exp(-t / tau): at t = tau the
    decaying part's relative error is 4.8 % at dt = tau / 10 and 5e-5 at dt = tau / 10,000
    (exp(1 / (2 n)) - 1 for n steps)."""
    C, K = 0.25 * UL_MIN_MMHG, 0.3
    reg = dataclasses.replace(AQUEOUS, facility=C)
    s = 8.0 / K  # mm^3 / MPa: tau = s / C = 0.0142 min
    tau = s / C
    times = tuple(tau * np.array([0.05, 0.1, 0.2, 0.4, 0.8, 1.6]))  # steps of 0.05 .. 0.8 tau
    v0, rows = _rigid_box_history(reg, K, 0.01, times)
    assert v0 == pytest.approx(8.0, rel=1e-12)
    P_ss = AQUEOUS.p_ev + AQUEOUS.production / C
    P = rows[0][1]
    assert P == pytest.approx(10 * MMHG + K * 0.01 / 8.0, rel=1e-12)  # the injection
    t_prev = 0.0
    for t, P_model, V in rows[1:]:
        assert V == pytest.approx(8.0, rel=1e-13)
        P = P_ss + (P - P_ss) / (1.0 + C * (t - t_prev) / s)
        t_prev = t
        assert P_model == pytest.approx(P, rel=1e-12)
    for n, err in ((10, 0.048), (10000, 0.5e-4)):
        be = (1.0 + 1.0 / n) ** -n  # the decaying part at t = tau
        assert abs(be / np.exp(-1.0) - 1) == pytest.approx(err, rel=0.05)


def _blood_decay_exact(x0, x_ss, s, C, emax, pb, t):
    """x(t) of the rigid-walled cavity with blood: (s + E'(x)) dx/dt = C (x_ss - x),
    x > 0 throughout: t(x) = s / C ln((x_ss - x0) / (x_ss - x)) + (E_max / p_b) / C
    exp(-x_ss / p_b) (Ei(u0) - Ei(u)), u = (x_ss - x) / p_b, inverted by brentq."""
    def t_of(x):
        u0, u = (x_ss - x0) / pb, (x_ss - x) / pb
        return (s / C * np.log((x_ss - x0) / (x_ss - x))
                + emax / pb / C * np.exp(-x_ss / pb) * (expi(u0) - expi(u)))

    return brentq(lambda x: t_of(x) - t, x_ss + 1e-15 * abs(x0), x0, xtol=1e-18, rtol=1e-15)


def test_exponential_compliance_cavity_with_outflow_follows_the_recursion_and_the_ode():
    """Rigid wall, a choroidal blood compartment of exponential compliance (E_max 60 uL,
    p_b 25 mmHg), Goldmann outflow: the pressure (40 mmHg after an injection, decaying to
    P_ss = 16.7 mmHg) follows the backward-Euler recursion solved by hand step by step
    (to 1e-12), and that recursion follows the ODE's closed form (through the exponential
    integral Ei) at first order: at dt = tau_0 / 2000 within 1e-4 at every named time."""
    K = 0.3
    reg = dataclasses.replace(AQUEOUS, **CHOROID_ESTIMATE)
    C, emax, pb = reg.facility, reg.blood_max, reg.blood_scale
    s = 8.0 / K
    # an injection that raises the pressure to ~40 mmHg: x0 E' + ... solved by hand
    x0 = 30 * MMHG
    dv = s * x0 + _blood(x0, emax, pb)
    times = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 30.0)
    v0, rows = _rigid_box_history(reg, K, dv, times)
    P0 = 10 * MMHG
    assert rows[0][1] == pytest.approx(P0 + x0, rel=1e-12)
    x_ss = AQUEOUS.p_ev + AQUEOUS.production / C - P0
    # the recursion by hand: s (x_n - x_{n-1}) + E(x_n) - E(x_{n-1}) = dt C (x_ss - x_n)
    x, t_prev = x0, 0.0
    for t, P_model, _ in rows[1:]:
        dt = t - t_prev
        rhs = s * x + _blood(x, emax, pb) + dt * C * x_ss
        x = brentq(lambda y: s * y + _blood(y, emax, pb) + dt * C * y - rhs, 0.0, x0,
                   xtol=1e-300, rtol=4 * np.finfo(float).eps)
        t_prev = t
        assert P_model == pytest.approx(P0 + x, rel=1e-12)
    # the recursion refined against the ODE: tau_0 the time constant at x0
    tau0 = (s + _blood_slope(x0, emax, pb)) / C
    n_per = 2000
    x, t, worst = x0, 0.0, 0.0
    for target in times:
        n = int(np.ceil((target - t) / (tau0 / n_per)))
        dt = (target - t) / n
        for _ in range(n):  # Newton on the monotone step equation
            rhs = s * x + _blood(x, emax, pb) + dt * C * x_ss
            y, step = x, 1.0
            while abs(step) > 1e-15 * abs(y):
                step = ((s + dt * C) * y + _blood(y, emax, pb) - rhs) / (
                    s + dt * C + _blood_slope(y, emax, pb))
                y -= step
            x = y
        t = target
        exact = _blood_decay_exact(x0, x_ss, s, C, emax, pb, t)
        worst = max(worst, abs((P0 + x) / (P0 + exact) - 1))
    assert worst < 1e-4  # measured 4.7e-5
    iop = [r[1] / MMHG for r in rows]  # 40.0, 36.9, 34.4, 30.9, 26.7, 22.5, 19.3, 17.6
    assert np.all(np.diff(iop) < 0) and iop[-1] > (P0 + x_ss) / MMHG


# --- the balance at every step of a soft wall ----------------------------------------------

POST_OP = step_times([60.0, 1440.0], first=5.0, ratio=2.0)
"""5, 15, 35, 60, 100, 180, 340, 660, 1440 min after the release."""


@pytest.fixture(scope="module")
def timeline():
    """A thin neo-Hookean sphere (96 hexahedra) pressurised to 15 mmHg and closed, with
    aqueous dynamics and a choroidal blood compartment; then a 10-minute 'tightening'
    (outer pressure 40 mmHg, 4 steps), a paracentesis of 50 uL at once, 20 uL drained over
    5 minutes, the outer load released at once, and post-operative relaxation to 1 hour and
    1 day. Returns the regulation constants, the rows of each step (stage, dt, report)."""
    m = generators.spherical_shell(10.0, 1.0, 4, 1, material="wall")
    m = m.replace(face_sets={**m.face_sets, "cavity": m.face_set("inner")})
    press = PressureLoad("iop", m, "inner", 0.0)
    squeeze = PressureLoad("buckle", m, "outer", 0.0)
    reg = dataclasses.replace(AQUEOUS, **CHOROID_ESTIMATE)
    cav = FluidCavity("cav", m, "cavity", bulk=2083.3, regulation=reg)
    model = solid_model(m, {"wall": neo_hookean("wall", 0.1)}, (press, squeeze, cav))
    d = shell_rigid_constraints(m)
    fix = (d, np.zeros(len(d)))
    on = ("solid", "buckle", "cav")
    rows = []

    def on_step(rec, model, q, theta):
        if rec.stage != "pressurise":
            rows.append((rec.stage, float(theta["cav"]["dt"]), model.report(q, theta, on)))

    stages = [
        Stage("pressurise", 2, fix, params={"iop": {"p": 15 * MMHG}}, active=("solid", "iop")),
        Stage("tighten", 4, fix, params={"buckle": {"p": 40 * MMHG}}, active=on,
              before=closing_hook("cav", "iop"), duration=10.0),
        Stage("paracentesis", 1, fix, params={"cav": {"paracentesis": 50.0}}, active=on),
        Stage("drain", 2, fix, params={"cav": {"drainage": 20.0}}, active=on, duration=5.0),
        Stage("release", 1, fix, params={"buckle": {"p": 0.0}}, active=on),
        Stage("post-op", len(POST_OP), fix, active=on, times=POST_OP)]
    sol = solve(model, stages, on_step=on_step)
    return reg, rows, sol


def test_volume_balance_closes_at_every_step(timeline):
    """At every step the enclosed volume's change equals the step's flows recomputed from
    the reported pressure alone: dt F produced, dt C (P - P_ev) out, the removed volumes,
    the blood expelled E(P) - E(P_prev) and the liquid's compression, to 1e-9 of the
    largest of them (measured 1e-14); the cumulative volumes are the sums of the steps'."""
    reg, rows, sol = timeline
    F, C, p_ev = reg.production, reg.facility, reg.p_ev
    P_ini, V_ini = sol.theta["cav"]["p_ini"], sol.theta["cav"]["v_ini"]
    assert P_ini == 15 * MMHG
    prev = (P_ini, V_ini, 0.0, 0.0)  # the closed state
    produced = outflow = 0.0
    assert [r[0] for r in rows] == ["tighten"] * 4 + ["paracentesis", "drain", "drain",
                                                      "release"] + ["post-op"] * len(POST_OP)
    for stage, dt, r in rows:
        P, V = r["cav/pressure_MPa"], r["cav/volume_mm3"]
        P0, V0, para0, drain0 = prev
        flows = {"produced": dt * F, "outflow": -dt * C * (P - p_ev),
                 "paracentesis": -(r["cav/paracentesis_mm3"] - para0),
                 "drainage": -(r["cav/drainage_mm3"] - drain0),
                 "blood": -(_blood(P - P_ini, reg.blood_max, reg.blood_scale)
                            - _blood(P0 - P_ini, reg.blood_max, reg.blood_scale)),
                 "compression": -V_ini * (P - P0) / 2083.3}
        scale = max(max(abs(f) for f in flows.values()), abs(V - V0))
        assert abs(V - V0 - sum(flows.values())) <= 1e-9 * scale, (stage, flows, V - V0)
        produced += dt * F
        outflow += dt * C * (P - p_ev)
        assert r["cav/produced_mm3"] == pytest.approx(produced, rel=1e-12)
        assert r["cav/aqueous_outflow_mm3"] == pytest.approx(outflow, rel=1e-12)
        assert abs(r["cav/balance_mm3"]) <= 1e-9 * max(abs(produced), abs(outflow), 1.0)
        assert r["cav/drained_mm3"] == r["cav/paracentesis_mm3"] + r["cav/drainage_mm3"]
        prev = (P, V, r["cav/paracentesis_mm3"], r["cav/drainage_mm3"])


def test_the_timeline_reaches_its_named_times(timeline):
    """Steps land on the stages' times: the clock reads 2.5 ... 10 min during the
    tightening, stands still through the paracentesis, 15 min after the drainage, and the
    post-operative steps end at 15 + step_times([60, 1440], 5, 2) min; the stages without
    duration take no time. Pressures: the tightening raises it, the paracentesis lowers
    it, and the eye ends near Goldmann's steady state P_ev + F / C (16.7 mmHg) a day
    later."""
    reg, rows, sol = timeline
    clock = [r["cav/time_min"] for _, _, r in rows]
    post = [15.0 + t for t in POST_OP]
    np.testing.assert_allclose(clock, [2.5, 5.0, 7.5, 10.0, 10.0, 12.5, 15.0, 15.0] + post,
                               rtol=1e-14)
    assert post[-1] == 1455.0 and 75.0 in post
    iop = [r["cav/pressure_mmHg"] for _, _, r in rows]
    assert iop[3] > 15.0 + 5 and iop[4] < iop[3] and iop[7] < iop[6]
    assert iop[-1] == pytest.approx(6.3 + 2.5 / 0.24, abs=0.1)
    assert sol.theta["cav"]["time"] == 1455.0 and sol.theta["cav"]["dt"] == 0.0


# --- gradients through time ------------------------------------------------------------------

def test_gradient_of_a_later_pressure_through_time_against_central_differences():
    """The pressure an hour after a tightening, a paracentesis and the release: its
    derivatives in the outflow facility (held over every step) and in the paracentesis
    volume (a stage's target) by the adjoint through time (eyefem.solve.transient: one
    adjoint per step, the produced and outflowed volumes chained back) against central
    differences of whole load paths (relative steps 1e-4 and 2e-5, Newton to 1e-11):
    agreement 1e-6 (measured 3e-9 and 1.4e-8)."""
    from eyefem.fem.cavity import cavity_pressures
    from eyefem.solve.solver import NewtonOptions
    from eyefem.solve.transient import Recorder, history_gradients, ramp_weights, total

    m = generators.spherical_shell(10.0, 1.0, 4, 1, material="wall")
    m = m.replace(face_sets={**m.face_sets, "cavity": m.face_set("inner")})
    reg = dataclasses.replace(AQUEOUS, **CHOROID_ESTIMATE)
    cav = FluidCavity("cav", m, "cavity", bulk=2083.3, regulation=reg)
    model = solid_model(m, {"wall": neo_hookean("wall", 0.1)},
                        (PressureLoad("iop", m, "inner", 0.0),
                         PressureLoad("buckle", m, "outer", 0.0), cav))
    d = shell_rigid_constraints(m)
    fix = (d, np.zeros(len(d)))
    on = ("solid", "buckle", "cav")
    options = NewtonOptions(rtol=1e-11, atol=1e-14)

    def run(facility=reg.facility, para=50.0, record=False):
        stages = [
            Stage("pressurise", 2, fix, params={"iop": {"p": 15 * MMHG}},
                  active=("solid", "iop")),
            Stage("tighten", 3, fix, params={"buckle": {"p": 40 * MMHG}}, active=on,
                  before=closing_hook("cav", "iop"), duration=10.0),
            Stage("paracentesis", 1, fix, params={"cav": {"paracentesis": para}}, active=on),
            Stage("release", 1, fix, params={"buckle": {"p": 0.0}}, active=on),
            Stage("post-op", 3, fix, active=on, times=(10.0, 30.0, 60.0))]
        theta = model.theta0()
        theta["cav"] = {**theta["cav"], "facility": facility}
        rec = Recorder(stages) if record else None
        sol = solve(model, stages, theta=theta, options=options, on_step=rec)
        return float(cav.pressures(sol.q, sol.theta["cav"])[0][0]), rec

    P, rec = run(record=True)
    value, grads = history_gradients(
        lambda q, th: cavity_pressures(q, th["cav"], cav.data, cav.dofs)[0][0], rec)
    assert value == pytest.approx(P, rel=1e-12)
    assert sum(g is not None for g in grads) == 8  # the steps after the closing
    g_fac = total(grads, "cav", "facility")
    g_para = total(grads, "cav", "paracentesis", ramp_weights(rec, "paracentesis"))
    h = 1e-4 * reg.facility
    fd_fac = (run(facility=reg.facility + h)[0] - run(facility=reg.facility - h)[0]) / (2 * h)
    fd_para = (run(para=50.0 + 1e-3)[0] - run(para=50.0 - 1e-3)[0]) / 2e-3
    assert g_fac == pytest.approx(fd_fac, rel=1e-6)
    assert g_para == pytest.approx(fd_para, rel=1e-6)
    assert g_fac < 0 and g_para < 0  # more outflow, more removed: a lower pressure


# --- the time axis of stages -----------------------------------------------------------------

def test_stage_times_are_checked_and_the_defaults_keep_the_load_factors():
    """A Stage's times must be n_steps increasing times ending at its duration; a stage
    without time-dependent terms solves the same states with or without a duration, and
    with times its steps end at times / duration, cut steps included."""
    from eyefem.solve.solver import NewtonOptions

    fix = (np.array([0]), np.zeros(1))
    with pytest.raises(ValueError, match="times"):
        Stage("s", 2, fix, times=(1.0, 0.5))
    with pytest.raises(ValueError, match="times"):
        Stage("s", 3, fix, times=(1.0, 2.0))
    with pytest.raises(ValueError, match="times"):
        Stage("s", 2, fix, times=(1.0, 2.0), duration=3.0)
    with pytest.raises(ValueError, match="duration"):
        Stage("s", 2, fix, duration=-1.0)
    assert Stage("s", 2, fix, times=(1, 4)).duration == 4.0
    m = generators.box(1.0, 1.0, 1.0, 1, 1, 2)
    model = solid_model(m, {"default": neo_hookean("default", 0.1)})
    z0 = node_dofs(m.node_set("z0"))
    top = node_dofs(m.node_set("z1"), "z")
    d = np.concatenate([z0, top])
    v = np.concatenate([np.zeros(len(z0)), np.full(len(top), 0.3)])
    runs = {}
    for key, kw in (("plain", {}), ("duration", {"duration": 30.0}),
                    ("times", {"times": (1.0, 3.0, 10.0)})):
        ts = []
        sol = solve(model, [Stage("pull", 3, (d, v), **kw)],
                    on_step=lambda rec, *a: ts.append(rec.t))
        runs[key] = (ts, sol.q)
    assert runs["plain"][0] == runs["duration"][0]
    np.testing.assert_array_equal(runs["plain"][1], runs["duration"][1])
    np.testing.assert_allclose(runs["times"][0], [0.1, 0.3, 1.0], rtol=1e-14)
    np.testing.assert_allclose(runs["times"][1], runs["plain"][1], rtol=0, atol=1e-9)
    # steps cut (Newton limited to 3 iterations, 70 % compression) still land on the times
    m = generators.box(1.0, 1.0, 1.0, 2, 2, 2)
    model = solid_model(m, {"default": neo_hookean("default", 0.1)})
    z0, top = node_dofs(m.node_set("z0")), node_dofs(m.node_set("z1"), "z")
    d = np.concatenate([z0, top])
    v = np.concatenate([np.zeros(len(z0)), np.full(len(top), -0.7)])
    ts = []
    solve(model, [Stage("squeeze", 2, (d, v), times=(9.0, 10.0))],
          options=NewtonOptions(max_iter=3), on_step=lambda rec, *a: ts.append(float(rec.t)))
    assert len(ts) > 2 and ts[-2:] == [0.9, 1.0] and np.all(np.diff(ts) > 0)


def test_step_times_land_on_the_named_times():
    ts = step_times([60.0, 1440.0, 2880.0, 10080.0, 129600.0], first=5.0, ratio=2.0)
    assert {60.0, 1440.0, 2880.0, 10080.0, 129600.0} <= set(ts)
    steps = np.diff(np.r_[0.0, ts])
    assert np.all(steps > 0) and ts[0] == 5.0 and np.all(steps[1:] <= 2.0 * 1.5 * steps[:-1])
    with pytest.raises(ValueError):
        step_times([], 1.0)


def test_condensed_pressure_compiles_once_per_shape(caplog):
    """The host evaluates the regulated cavity's pressure at every line-search trial and
    report: after the first call, a call with new values of the same shape compiles
    nothing (a loop traced at each call compiled anew and kept every executable: a coarse
    timeline run's peak memory 1.57 GB instead of 0.95)."""
    from eyefem.fem.regulation import condensed_pressure

    def args(rhs):
        return [jnp.array([v]) for v in (rhs, 1.0, 2.0, 60.0, 0.003)]

    first = condensed_pressure(*args(1e-3))
    with jax.log_compiles(True), caplog.at_level("WARNING"):
        caplog.clear()
        second = condensed_pressure(*args(2e-3))
    compiled = [r.getMessage() for r in caplog.records if "Compiling" in r.getMessage()]
    assert not compiled, compiled
    assert float(second[0]) > float(first[0]) > 0.0

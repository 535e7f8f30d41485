"""Volume regulation of a closed fluid cavity over time (issue 74): aqueous production and
outflow (Goldmann's law), a choroidal blood compartment, paracentesis and drainage, as
terms of the incremental energy of a backward-Euler step.

The laws, per cavity (x = P - P_ini, the pressure above the closing pressure; time in
minutes; every flow in mm^3 = uL):

- liquid (the seed's law): at pressure P the liquid fills its content less
  V_ini x / K (K the bulk modulus), less C_out x in the optional linear reservoir;
- **aqueous production and outflow** (Goldmann's law): the content gains F per minute
  and loses C (P - P_ev) per minute, C the outflow facility, P_ev the episcleral venous
  pressure, F the production net of the pressure-independent (uveoscleral) outflow;
- **choroidal blood**: the choroid holds blood that it gives up as the pressure rises,
  E(x) = E_max (1 - exp(-x / p_b)) expelled for x >= 0, and takes up (choroidal
  swelling) as it falls, E(x) = -E_max (1 - exp(x / p_b)) for x < 0: a compliance
  c_b = E_max / p_b at the closing pressure (the measured linear slope), a finite volume
  E_max that is exhausted a few p_b above (the living eye stiffens to the dead eye's
  rigidity once the pressure passes the arterial pressure). Elastic (no time constant);
- **paracentesis and drainage**: volumes removed by the surgeon (cumulative, mm^3),
  params ramped by stages like the injected volume dV.

Backward Euler over a step of dt minutes ending at the pressure P: the cavity's enclosed
volume V(q) equals what fills it,

    V = vol_n(P) = W_n - x / a - (C_out + dt C) x - E(x),     a = K / V_ini,
    W_n = V_ini + dV - paracentesis - drainage + Prod_n + dt F - Out_n - dt C (P_ini - P_ev)

with Prod_n, Out_n the produced and outflowed volumes at the end of the last step; that
is, change of volume = dV + produced - outflow - drained - blood expelled - compression,
the balance reported at every step.

**The incremental potential.** The balance is the stationarity in P of the mixed
potential Pi_n(q, P) = Pi_wall(q) + Phi_n(P) - P V(q) + P_ini W_n, where

    Phi_n(P) = W_n x - x^2 / (2 a) - (C_out + dt C) x^2 / 2 - Ehat(x),   Ehat' = E,

is the complementary energy of what fills the cavity (Phi_n' = vol_n). Its Goldmann part,
dt F x - dt C x^2 / 2 - dt C (P_ini - P_ev) x, is, up to a constant, minus the step's
dissipation potential dt [C (P - P_ev)^2 / 2 - F P]: stationarity in P gives
backward-Euler's Goldmann balance, stationarity in q the wall loaded by P. Phi_n is
strictly concave, so the pressure, one scalar per cavity, is condensed exactly: the
kernel solves vol_n(P) = V(q) (a safeguarded Newton iteration, to roundoff) and the
cavity's energy is the reduced potential Pi_c(V) = max_P [Phi_n(P) - P V] + P_ini W_n, a
function of q alone with dPi_c/dV = -P and d2Pi_c/dV2 = alpha = a / (1 + a (C_out + dt
C) + a E'(x)). The term keeps the seed's structure: a follower pressure and a rank-one
tangent alpha g g^T (the linear solver's Woodbury path), no new unknown and no saddle
point in P; Newton, the line search and the adjoint see an ordinary energy. Without
regulation (dt = 0, E_max = 0) Pi_c is the seed's -P_ini e + K e^2 / (2 V_ini)
exactly. The root is differentiated implicitly (``jax.custom_jvp``), so every order of
autodiff (residual, tangent-vector products, design derivatives) is exact.

History: Prod, Out and the clock (``time``, minutes) are params updated after each
converged step (:meth:`eyefem.fem.cavity.FluidCavity.advance`); the load path sets
``dt`` from the stage's duration (:class:`eyefem.solve.loadpath.Stage`).

Parameter sources (clinical units; :data:`AQUEOUS` holds them in the model's):

- facility C = 0.24 +- 0.08 uL/min/mmHg (pneumatonography; 0.29 +- 0.09 by digital
  Schiotz tonography), 56 healthy eyes aged 41-68: Kazemi et al., Invest Ophthalmol Vis
  Sci 58:204 (2017);
- episcleral venous pressure P_ev = 6.3 +- 2.8 mmHg, computerised venomanometry, 10
  eyes of 5 healthy volunteers: Sit et al., Exp Eye Res 92:537 (2011); a population
  mean of about 8 mmHg is quoted in Exp Eye Res 92:318 (2011),
  doi:10.1016/j.exer.2011.03.011 (methods and reported values reviewed by Sit and
  McLaren, Exp Eye Res 93:291, 2011);
- production F = 2.5 uL/min, the average rate at which aqueous enters the normal human
  anterior chamber (Toris, "Aqueous humor dynamics", book chapter, CRC Press,
  doi:10.1201/b16796-3), here net of uveoscleral outflow. With these C, P_ev and F
  Goldmann's steady state is P_ev + F / C = 16.7 mmHg;
- choroidal blood: the choroid thickens 3.4 um per mmHg of IOP lowering (17 eyes after
  trabeculectomy: "Change in choroidal thickness and axial length with change in
  intraocular pressure after trabeculectomy", Br J Ophthalmol 98:976, 2014), its vessel
  lumen 1.5 um per mmHg (95 % CI 0.8-2.1) of that (30 eyes after glaucoma procedures:
  Zhang et al., Invest Ophthalmol Vis Sci 58:3278, 2017); over the sclera's 16.3 cm^2
  (Olsen et al., Am J Ophthalmol 125:237, 1998) the vessel part is c_b = 1.5e-3 mm x
  1630 mm^2 = 2.4 uL/mmHg, an upper bound of the blood's compliance (the choroid covers
  less than the whole sclera, and these are changes over days). Living eyes stiffen to the dead eye's rigidity once the IOP passes
  the blood pressure (rabbits: Eisenlohr and Langham, Invest Ophthalmol 1:63, 1962): the
  content is exhausted by about 3 p_b above the closing pressure, p_b = 25 mmHg for an
  exhaustion near 90 mmHg, so E_max = c_b p_b = 60 uL (:data:`CHOROID_ESTIMATE`, an
  estimate from these sources, not a measurement). Note that the living-eye rigidity the
  ``physiological`` preset is fitted to (fast injections) already includes the blood
  pressed out during the injection: the compartment on that wall counts it twice.

Length: the laws, the condensed pressure and its implicit derivative, the report's
volumes and the time helpers; about 320 lines.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.fem.units import MMHG

UL_MIN_MMHG = 1.0 / MMHG
"""One uL/min/mmHg in mm^3 / (min MPa) (the model's facility unit)."""

MINUTE, HOUR, DAY, WEEK = 1.0, 60.0, 1440.0, 10080.0
"""Time units in minutes (the model's time unit)."""

MONTH = 30.0 * DAY
"""A month of 30 days, minutes."""

REGULATION_KEYS = ("facility", "p_ev", "production", "blood_max", "blood_scale",
                   "paracentesis", "drainage", "aq_produced", "aq_outflow")
"""Per-cavity params of a regulated cavity (beside the seed's p_ini, v_ini, bulk, dv,
c_out); ``dt`` and ``time`` are scalars shared by the cavities."""

HISTORY_KEYS = ("time", "aq_produced", "aq_outflow")
"""Params that hold the state at the end of the last converged step: set by
:meth:`FluidCavity.advance`, never ramped by a stage."""


@dataclasses.dataclass(frozen=True)
class Regulation:
    """Constants of a cavity's volume regulation, in the model's units (scalars, or one
    value per cavity). Defaults: no regulation (every flow zero); :data:`AQUEOUS` and
    :data:`CHOROID_ESTIMATE` hold the published values, :meth:`clinical` takes clinical
    units.

    Attributes:
      facility: outflow facility C, mm^3 / (min MPa) (>= 0).
      p_ev: episcleral venous pressure P_ev, MPa.
      production: aqueous production F (net of uveoscleral outflow), mm^3 / min.
      blood_max: choroidal blood E_max expelled at most (and taken up at most), mm^3 (>= 0).
      blood_scale: pressure scale p_b of the blood compartment, MPa (> 0).
    """

    facility: float | Sequence[float] = 0.0
    p_ev: float | Sequence[float] = 0.0
    production: float | Sequence[float] = 0.0
    blood_max: float | Sequence[float] = 0.0
    blood_scale: float | Sequence[float] = 25.0 * MMHG

    @classmethod
    def clinical(cls, facility_ul_min_mmhg=0.0, episcleral_mmhg=0.0, production_ul_min=0.0,
                 blood_max_ul=0.0, blood_scale_mmhg=25.0) -> "Regulation":
        """The constants in clinical units (uL/min/mmHg, mmHg, uL/min, uL, mmHg)."""
        return cls(np.asarray(facility_ul_min_mmhg, float) * UL_MIN_MMHG,
                   np.asarray(episcleral_mmhg, float) * MMHG,
                   np.asarray(production_ul_min, float),
                   np.asarray(blood_max_ul, float), np.asarray(blood_scale_mmhg, float) * MMHG)

    def params(self, n: int, label: str) -> dict:
        """The term's params (n,) of these constants, checked; histories at zero."""
        out = {}
        for key, lo, unit in (("facility", 0.0, "mm^3/(min MPa)"), ("p_ev", -np.inf, "MPa"),
                              ("production", -np.inf, "mm^3/min"), ("blood_max", 0.0, "mm^3"),
                              ("blood_scale", 0.0, "MPa")):
            a = np.broadcast_to(np.asarray(getattr(self, key), np.float64), (n,)).copy() \
                if np.ndim(getattr(self, key)) == 0 else np.asarray(getattr(self, key), float)
            if a.shape != (n,) or not np.all(np.isfinite(a)) or np.any(a < lo) \
                    or (key == "blood_scale" and np.any(a <= 0)):
                raise ValueError(f"cavity '{label}': regulation {key} = {a.tolist()} {unit}; "
                                 f"expected a scalar or ({n},), finite, "
                                 f"{'> 0' if key == 'blood_scale' else f'>= {lo}'}")
            out[key] = a
        for key in ("paracentesis", "drainage", "aq_produced", "aq_outflow"):
            out[key] = np.zeros(n)
        return out


AQUEOUS = Regulation(facility=0.24 * UL_MIN_MMHG, p_ev=6.3 * MMHG, production=2.5)
"""Aqueous dynamics of the normal human eye (module docstring: Kazemi et al. 2017, Sit et
al. 2011, Toris 2014); no blood compartment."""

CHOROID_ESTIMATE = dict(blood_max=60.0, blood_scale=25.0 * MMHG)
"""The choroidal blood compartment estimated in the module docstring (E_max 60 uL,
p_b 25 mmHg: c_b = 2.4 uL/mmHg at the closing pressure); ``dataclasses.replace(AQUEOUS,
**CHOROID_ESTIMATE)`` adds it."""


# --- the laws (pure JAX, vectorised over the cavities) -----------------------------------

def blood_expelled(x, blood_max, blood_scale):
    """Blood E (mm^3) expelled at x = P - P_ini (MPa) above the closing pressure (< 0:
    taken up below it); odd, increasing, bounded by +-E_max, slope E_max / p_b at 0."""
    s = x / blood_scale
    return blood_max * jnp.where(x >= 0, -jnp.expm1(-jnp.maximum(s, 0.0)),
                                 jnp.expm1(jnp.minimum(s, 0.0)))


def _blood_energy(x, blood_max, blood_scale):
    """Ehat(x) = integral_0^x E (N mm): E_max (|x| - p_b (1 - exp(-|x| / p_b)))."""
    ax = jnp.abs(x)
    return blood_max * (ax + blood_scale * jnp.expm1(-ax / blood_scale))


def _blood_compliance(x, blood_max, blood_scale):
    """dE/dx (mm^3 / MPa)."""
    return blood_max / blood_scale * jnp.exp(-jnp.abs(x) / blood_scale)


def _lhs(x, m, a, bmax, bscale):
    """f(x) = m x + a E(x): the pressure equation is f(x) = a (W - V)."""
    return m * x + a * blood_expelled(x, bmax, bscale)


ROOT_ITERATIONS = 60
"""Safeguarded Newton iterations of the condensed pressure (quadratic from the bracket;
a step leaving the bracket bisects it, so 60 halvings bound the worst case)."""


@jax.custom_jvp
def condensed_pressure(rhs, m, a, bmax, bscale):
    """The root x of m x + a E(x) = rhs (arrays (n,)): the pressure above P_ini, MPa.

    f(x) = m x + a E(x) increases with slope in [m, m + a E_max / p_b] (m >= 1), so the
    root lies between rhs / m and rhs / (m + a E_max / p_b); Newton steps that leave the
    bracket bisect it. Differentiated implicitly (its JVP rule), to every order."""
    return _root(rhs, m, a, bmax, bscale)


@jax.jit
def _root(rhs, m, a, bmax, bscale):
    """:func:`condensed_pressure`'s iteration, compiled once per shape, so that the host's
    calls outside a traced function (the cavity's pressures and reports at every
    line-search trial) reuse one executable instead of tracing the loop at each call."""
    M = m + a * bmax / bscale
    lo = jnp.minimum(rhs / m, rhs / M)
    hi = jnp.maximum(rhs / m, rhs / M)

    def body(_, state):
        x, lo, hi = state
        f = _lhs(x, m, a, bmax, bscale) - rhs
        lo = jnp.where(f < 0, x, lo)
        hi = jnp.where(f > 0, x, hi)
        xn = x - f / (m + a * _blood_compliance(x, bmax, bscale))
        xn = jnp.where((xn > lo) & (xn < hi), xn, 0.5 * (lo + hi))
        return jnp.where(f == 0, x, xn), lo, hi

    x, _, _ = jax.lax.fori_loop(0, ROOT_ITERATIONS, body, (0.5 * (lo + hi), lo, hi))
    return x


@condensed_pressure.defjvp
def _condensed_pressure_jvp(primals, tangents):
    rhs, m, a, bmax, bscale = primals
    drhs, dm, da, dbmax, dbscale = tangents
    x = condensed_pressure(rhs, m, a, bmax, bscale)
    _, df = jax.jvp(lambda m_, a_, b_, s_: _lhs(x, m_, a_, b_, s_), (m, a, bmax, bscale),
                    (dm, da, dbmax, dbscale))
    return x, (drhs - df) / (m + a * _blood_compliance(x, bmax, bscale))


def _get(params, key, n, dtype):
    return jnp.broadcast_to(jnp.asarray(params[key], dtype), (n,))


def regulated_state(V, params) -> dict:
    """The regulated cavity law at volumes V (n_cav,) mm^3: a dict of (n_cav,) arrays:
    P (MPa), Pi (N mm), alpha (-dP/dV, MPa / mm^3) and the volumes of the balance
    (mm^3, cumulative since the closing): injected, drained, produced, outflow (Goldmann),
    blood (expelled), compressed (the liquid's), reservoir (C_out x)."""
    n, dt_ = V.shape[0], V.dtype
    g = {k: _get(params, k, n, dt_) for k in ("p_ini", "v_ini", "bulk", "dv", "c_out", "dt")
         + REGULATION_KEYS}
    a = g["bulk"] / g["v_ini"]
    c_step = g["dt"] * g["facility"]
    c_rest = g["c_out"] + c_step
    produced = g["aq_produced"] + g["dt"] * g["production"]
    drained = g["paracentesis"] + g["drainage"]
    W = (g["v_ini"] + g["dv"] - drained + produced - g["aq_outflow"]
         - c_step * (g["p_ini"] - g["p_ev"]))
    x = condensed_pressure(a * (W - V), 1.0 + a * c_rest, a, g["blood_max"], g["blood_scale"])
    E = blood_expelled(x, g["blood_max"], g["blood_scale"])
    # the reduced potential max_P [Phi_n(P) - P V] + P_ini W, written with the root's
    # identity x / a = W - V - c_rest x - E (so that K = 0, a pressure-controlled liquid,
    # needs no division by a): x (W - V) / 2 + x E / 2 - Ehat(x) - P_ini (V - W)
    pi = (0.5 * x * (W - V) + 0.5 * x * E - _blood_energy(x, g["blood_max"], g["blood_scale"])
          - g["p_ini"] * (V - W))
    alpha = a / (1.0 + a * c_rest + a * _blood_compliance(x, g["blood_max"], g["blood_scale"]))
    P = g["p_ini"] + x
    return {"P": P, "Pi": pi, "alpha": alpha, "injected": g["dv"], "drained": drained,
            "produced": produced, "outflow": g["aq_outflow"] + c_step * (P - g["p_ev"]),
            "blood": E, "compressed": jnp.where(a > 0, x / jnp.where(a > 0, a, 1.0), 0.0),
            "reservoir": g["c_out"] * x}


def advanced_history(P, params) -> dict:
    """The history after a converged step of ``params["dt"]`` minutes ending at the
    pressure P (numpy or JAX, one value per cavity): the clock, the produced and the
    outflowed volumes moved on by backward Euler."""
    dt = params["dt"]
    return {"time": params["time"] + dt,
            "aq_produced": params["aq_produced"] + dt * params["production"],
            "aq_outflow": params["aq_outflow"] + dt * params["facility"] * (P - params["p_ev"])}


def balance(V, state, v_ini) -> np.ndarray:
    """The volume balance's residual (n_cav,), mm^3: V - V_ini - (injected - drained +
    produced - outflow - blood - compressed - reservoir); zero at every converged step
    (to the roundoff of the condensed pressure)."""
    s = {k: np.asarray(v) for k, v in state.items()}
    return (np.asarray(V) - np.asarray(v_ini)
            - (s["injected"] - s["drained"] + s["produced"] - s["outflow"] - s["blood"]
               - s["compressed"] - s["reservoir"]))


# --- time: the steps of a stage ----------------------------------------------------------

def step_times(named: Sequence[float], first: float, ratio: float = 2.0) -> tuple:
    """Step end times (minutes from the stage start) that land on every ``named`` time:
    the first step lasts ``first``, each next one ``ratio`` times the last, and a step is
    stretched (up to 1.5 times) or shortened to end on the next named time."""
    named = sorted(float(t) for t in named)
    if not named or named[0] <= 0 or first <= 0 or ratio < 1.0:
        raise ValueError(f"step_times: named times {named} (> 0), first {first} (> 0) and "
                         f"ratio {ratio} (>= 1)")
    out, t, dt = [], 0.0, float(first)
    for target in named:
        while target - t > 1.5 * dt:
            t += dt
            out.append(t)
            dt *= ratio
        if target > t:
            t = target
            out.append(t)
    return tuple(out)

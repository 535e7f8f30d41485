"""Discretisation uncertainty from three grids: observed order, Richardson, GCI.

The procedure of Celik et al. 2008 (J. Fluids Eng. 130:078001, "Procedure for estimation
and reporting of uncertainty due to discretization in CFD applications") with Roache's
grid convergence index (safety factor Fs = 1.25 for three grids), for refinement ratios
that need not be constant. Pure numpy; no eye model needed.

Grids are ordered fine to coarse: h1 < h2 < h3 with values phi1, phi2, phi3. For the eye
the grid size measure is h = 1 / n, n the elements per cubed-sphere patch edge (the wall
keeps 4 element layers at every level, so refinement is in-plane only; the limit h -> 0 is
the 4-layer through-thickness model, not the continuum; levels with the suffix "x2" split
the layers to measure that part apart).

  r21 = h2 / h1, r32 = h3 / h2, eps21 = phi2 - phi1, eps32 = phi3 - phi2
  s = sign(eps32 / eps21); s < 0 is oscillatory convergence (no p, no extrapolation)
  p = (ln|eps32 / eps21| + q(p)) / ln r21,  q(p) = ln((r21^p - s) / (r32^p - s))
  phi_ext = (r21^p phi1 - phi2) / (r21^p - 1)
  e_a21 = |(phi1 - phi2) / phi1|, e_ext21 = |(phi_ext - phi1) / phi_ext|
  GCI_fine21 = Fs e_a21 / (r21^p - 1)

Celik's Eq. (5a) takes |.| of the right-hand side, which turns a monotone divergence
(differences growing as h shrinks) into a positive p; here p is solved without the
absolute value, and p <= 0 is reported as divergence, never as an order.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

SAFETY_FACTOR = 1.25
"""Roache's factor of safety for a three-grid study with an observed order."""

MONOTONE = "monotone"
OSCILLATORY = "oscillatory"
DIVERGENT = "divergent"
INDETERMINATE = "indeterminate"


@dataclasses.dataclass(frozen=True)
class ThreeGridStudy:
    """Result of the three-grid procedure for one quantity (grids fine -> coarse).

    Attributes:
      h: grid sizes (h1, h2, h3), h1 < h2 < h3.
      values: (phi1, phi2, phi3) on those grids.
      r21, r32: refinement ratios h2 / h1, h3 / h2.
      behaviour: "monotone", "oscillatory" (eps32 / eps21 < 0), "divergent" (no
        positive order fits: the differences do not shrink with h) or "indeterminate"
        (a difference is zero, or the iteration for p did not converge).
      p: observed order (nan unless monotone).
      extrapolated: Richardson extrapolated value phi_ext21 (nan unless monotone).
      e_a21: approximate relative error |phi1 - phi2| / |phi1|.
      e_ext21: extrapolated relative error |phi_ext - phi1| / |phi_ext| (nan unless
        monotone).
      gci_fine: GCI_fine21, relative (0.05 = 5 %; nan unless monotone).
      gci_medium: GCI of grid 2 from the same extrapolation, Fs |phi_ext - phi2| / |phi2|.
      asymptotic_ratio: GCI32 / (r21^p GCI21), ~1 in the asymptotic range (Roache).
      spread: (max - min) / |phi1| of the three values, the oscillation amplitude used
        for non-monotone sequences (not a GCI).
      note: why a number is missing, or a warning (empty when all is well): an order
        outside 0.5..4 or an extrapolated value of the other sign than phi1.
    """

    h: tuple[float, float, float]
    values: tuple[float, float, float]
    r21: float
    r32: float
    behaviour: str
    p: float
    extrapolated: float
    e_a21: float
    e_ext21: float
    gci_fine: float
    gci_medium: float
    asymptotic_ratio: float
    spread: float
    note: str = ""

    def as_dict(self) -> dict:
        """JSON-ready dict (nan -> None)."""
        def clean(v):
            if isinstance(v, tuple):
                return [clean(x) for x in v]
            if isinstance(v, float) and not math.isfinite(v):
                return None
            return v
        return {k: clean(v) for k, v in dataclasses.asdict(self).items()}


def observed_order(r21: float, r32: float, eps21: float, eps32: float,
                   tol: float = 1e-12, max_iter: int = 200) -> tuple[float, bool]:
    """Observed order p by fixed-point iteration of Celik's Eq. (5) (signed, see module).

    Args:
      r21, r32: refinement ratios (> 1).
      eps21, eps32: phi2 - phi1 and phi3 - phi2 (same sign: monotone sequence).
    Returns:
      (p, converged). p <= 0 means the differences do not shrink with h.
    """
    s = 1.0 if eps32 / eps21 > 0 else -1.0
    lr = math.log(abs(eps32 / eps21))
    p = lr / math.log(r21)  # the constant-ratio answer as the start
    for _ in range(max_iter):
        if p == 0.0:
            p = 1e-9
        q = math.log((r21 ** p - s) / (r32 ** p - s))
        p_new = (lr + q) / math.log(r21)
        if not math.isfinite(p_new):
            return float("nan"), False
        if abs(p_new - p) <= tol * max(1.0, abs(p_new)):
            return p_new, True
        p = p_new
    return p, False


def three_grid_study(h, values, safety_factor: float = SAFETY_FACTOR) -> ThreeGridStudy:
    """The three-grid procedure for one quantity.

    Args:
      h: three grid sizes, any order (sorted here fine -> coarse), all distinct and > 0.
      values: the quantity on those grids (same order as h).
      safety_factor: Fs of the GCI (1.25).
    Returns:
      ThreeGridStudy; behaviour says whether p, the extrapolation and the GCI exist.
    """
    h = np.asarray(h, float)
    values = np.asarray(values, float)
    if h.shape != (3,) or values.shape != (3,):
        raise ValueError(f"three_grid_study: need 3 grid sizes and 3 values, got h {h.shape}, "
                         f"values {values.shape}; pass one consecutive triple of levels")
    if np.any(h <= 0) or len(np.unique(h)) != 3:
        raise ValueError(f"three_grid_study: grid sizes h={h.tolist()} must be distinct and > 0")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"three_grid_study: values {values.tolist()} must be finite "
                         "(a failed run?)")
    order = np.argsort(h)
    (h1, h2, h3), (f1, f2, f3) = h[order], values[order]
    r21, r32 = h2 / h1, h3 / h2
    eps21, eps32 = f2 - f1, f3 - f2
    scale = abs(f1) if f1 != 0 else max(abs(f2), abs(f3), 1e-300)
    spread = float((values.max() - values.min()) / scale)
    e_a21 = abs(eps21) / scale
    nan = float("nan")
    common = {"h": (float(h1), float(h2), float(h3)),
              "values": (float(f1), float(f2), float(f3)),
              "r21": float(r21), "r32": float(r32), "e_a21": float(e_a21), "spread": spread}

    def without(behaviour, note, p=nan):
        return ThreeGridStudy(**common, behaviour=behaviour, p=p, extrapolated=nan,
                              e_ext21=nan, gci_fine=nan, gci_medium=nan,
                              asymptotic_ratio=nan, note=note)

    if eps21 == 0.0 or eps32 == 0.0:
        return without(INDETERMINATE, "a difference between grids is exactly zero")
    if eps32 / eps21 < 0:
        return without(OSCILLATORY, "eps32 / eps21 < 0: the values oscillate with h; "
                       "no order or extrapolation, spread given instead")
    p, ok = observed_order(r21, r32, eps21, eps32)
    if not ok:
        return without(INDETERMINATE, "the fixed-point iteration for p did not converge")
    if p <= 0:
        return without(DIVERGENT, "the differences grow as h shrinks (p <= 0)", p=float(p))
    rp = r21 ** p
    ext = (rp * f1 - f2) / (rp - 1)
    gci_fine = safety_factor * e_a21 / (rp - 1)
    gci_medium = safety_factor * abs(ext - f2) / abs(f2) if f2 != 0 else nan
    gci32 = safety_factor * abs(eps32) / abs(f2) / (r32 ** p - 1) if f2 != 0 else nan
    e_ext = abs(ext - f1) / abs(ext) if ext != 0 else nan
    note = ""
    if p < 0.5 or p > 4.0:
        note = f"observed order p = {p:.2f} is far from the element's order (1..2): " \
               "not in the asymptotic range, treat the GCI with caution"
    elif ext * f1 < 0:
        note = f"the extrapolated value {ext:.4g} has the other sign than the values: " \
               "not credible (a quantity that tends to zero, or not asymptotic)"
    return ThreeGridStudy(**common, behaviour=MONOTONE, p=float(p), extrapolated=float(ext),
                          e_ext21=float(e_ext), gci_fine=float(gci_fine),
                          gci_medium=float(gci_medium),
                          asymptotic_ratio=float(gci32 / (rp * gci_fine)), note=note)


def relative_gci(value: float, extrapolated: float,
                 safety_factor: float = SAFETY_FACTOR) -> float:
    """GCI of any grid from an extrapolated value: Fs |phi_ext - phi| / |phi| (relative).

    For the finest grid of the triple this equals GCI_fine21; for a coarser grid it is its
    estimated discretisation error (times Fs) against the finest triple's extrapolation.
    """
    if not (math.isfinite(value) and math.isfinite(extrapolated)) or value == 0:
        return float("nan")
    return safety_factor * abs(extrapolated - value) / abs(value)


# ---------------------------------------------------------------- four or more grids

LSQ_SAFETY_FACTORS = (1.25, 3.0)
"""Safety factors of the least-squares procedure: a fit of the free order in 0.5..2.1
that lies within the data's scatter, and every other case."""

LSQ_ORDER_RANGE = (0.5, 2.1)
"""Free orders for which the least-squares procedure keeps the free-order fit."""

LSQ_ORDER_BOUNDS = (0.02, 8.0)
"""Orders the free-order fit searches."""

LSQ_FITS = {"p": None, "1": (1.0,), "2": (2.0,), "12": (1.0, 2.0)}
"""The least-squares procedure's fits: phi0 + alpha h^p (p free), and phi0 plus terms of
the fixed orders given."""


@dataclasses.dataclass(frozen=True)
class LeastSquaresStudy:
    """Discretisation uncertainty of one quantity from four or more grids, by the
    least-squares procedure of Eca and Hoekstra (2014, J. Comput. Phys. 262:104, "A
    procedure for the estimation of the numerical uncertainty of CFD calculations based on
    grid refinement studies"): each fit unweighted and with the weights w_i proportional to
    1 / h_i, the one with the smaller standard deviation kept.

    Attributes:
      h, values: grid sizes fine -> coarse and the quantity on them.
      p: order of the free-order fit phi0 + alpha h^p (LSQ_ORDER_BOUNDS; nan where the
        values are the same on every grid).
      fit: the fit the error comes from: "p" (0.5 <= p < 2.1), else the fixed-order fit
        with the smallest standard deviation: "2" or "12" (p >= 2.1), "1", "2" or "12"
        (p < 0.5); "12" from five grids (two degrees of freedom left).
      extrapolated: that fit's phi0, the estimate of the exact value.
      sigma: that fit's standard deviation, sqrt(sum n w_i (phi_i - fit_i)^2 / (n - q)), q
        the fitted coefficients, w_i = 1 / n unweighted.
      data_range: (max phi - min phi) / (n - 1).
      safety_factor: 1.25 where fit == "p" and sigma < data_range, else 3.
      error: |fit_i - phi0| per grid, the fit's discretisation error.
      uncertainty: U_i per grid (absolute): Fs error_i + sigma + |phi_i - fit_i| where
        sigma < data_range, else 3 sigma / data_range (error_i + sigma + |phi_i - fit_i|).
      note: a warning (empty when the free-order fit is used and fits the data).
    """

    h: tuple
    values: tuple
    p: float
    fit: str
    extrapolated: float
    sigma: float
    data_range: float
    safety_factor: float
    error: tuple
    uncertainty: tuple
    note: str = ""

    def relative(self, i: int = 0) -> float:
        """U_i / |phi_i| of grid i (0: the finest)."""
        v = self.values[i]
        return self.uncertainty[i] / abs(v) if v != 0 else float("nan")

    def as_dict(self) -> dict:
        """JSON-ready dict (nan -> None), with the finest grid's relative uncertainty."""
        d = {k: (list(v) if isinstance(v, tuple) else v)
             for k, v in dataclasses.asdict(self).items()}
        d["relative_fine"] = self.relative(0)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in d.items()}


def _fixed_order_fit(h, f, orders, weighted=False):
    """Least squares phi0 + sum_k a_k h^orders[k], unweighted or with the weights
    w_i = (1 / h_i) / sum_j (1 / h_j) (the finer grids count more): (phi0, fitted values,
    sigma), sigma = sqrt(sum n w_i (phi_i - fit_i)^2 / (n - q))."""
    n = len(h)
    w = (1.0 / h) / np.sum(1.0 / h) if weighted else np.full(n, 1.0 / n)
    a = np.column_stack([np.ones_like(h)] + [h ** q for q in orders])
    sw = np.sqrt(w)
    coef = np.linalg.lstsq(a * sw[:, None], f * sw, rcond=None)[0]
    fit = a @ coef
    dof = n - a.shape[1]
    return float(coef[0]), fit, float(np.sqrt(np.sum(n * w * (f - fit) ** 2) / dof))


def _best_fit(h, f, orders):
    """The unweighted or weighted fit of ``orders``, whichever has the smaller sigma."""
    return min((_fixed_order_fit(h, f, orders, wt) for wt in (False, True)),
               key=lambda r: r[2])


def _free_order_fit(scale, f):
    """Least squares phi0 + alpha h^p over p in [LSQ_ORDER_BOUNDS], unweighted or weighted,
    whichever has the smaller sigma: (p, phi0, fitted values, sigma); p at a bound where
    the best fit lies beyond it. scale: h / max h (h^p = 1 on the coarsest grid: the fit
    well conditioned at any p)."""
    from scipy.optimize import minimize_scalar

    grid = np.linspace(*np.log(LSQ_ORDER_BOUNDS), 241)
    best = None
    for weighted in (False, True):
        def ss(logp):
            return _fixed_order_fit(scale, f, (math.exp(logp),), weighted)[2]

        k = int(np.argmin([ss(x) for x in grid]))
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
        res = minimize_scalar(ss, bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-10})
        p = math.exp(res.x) if res.fun <= ss(grid[k]) else math.exp(grid[k])
        phi0, fit, sigma = _fixed_order_fit(scale, f, (p,), weighted)
        if best is None or sigma < best[3]:
            best = (p, phi0, fit, sigma)
    return best


def least_squares_study(h, values) -> LeastSquaresStudy:
    """The least-squares procedure (LeastSquaresStudy) for one quantity on n >= 4 grids.

    Args:
      h: grid sizes, any order (sorted here fine -> coarse), distinct and > 0.
      values: the quantity on those grids (same order), finite.
    """
    h = np.asarray(h, float)
    f = np.asarray(values, float)
    if h.ndim != 1 or h.shape != f.shape or len(h) < 4:
        raise ValueError(f"least_squares_study: need n >= 4 grid sizes and as many values, "
                         f"got h {h.shape}, values {f.shape}; three grids: three_grid_study")
    if np.any(h <= 0) or len(np.unique(h)) != len(h):
        raise ValueError(f"least_squares_study: grid sizes h={h.tolist()} must be distinct "
                         "and > 0")
    if not np.all(np.isfinite(f)):
        raise ValueError(f"least_squares_study: values {f.tolist()} must be finite "
                         "(a failed run?)")
    order = np.argsort(h)
    h, f = h[order], f[order]
    n = len(h)
    data_range = float((f.max() - f.min()) / (n - 1))
    if data_range == 0.0:
        zero = tuple(0.0 for _ in f)
        return LeastSquaresStudy(tuple(h.tolist()), tuple(f.tolist()), float("nan"), "p",
                                 float(f[0]), 0.0, 0.0, LSQ_SAFETY_FACTORS[0], zero, zero,
                                 "the values are the same on every grid")
    scale = h / h.max()
    p, phi0, fit, sigma = _free_order_fit(scale, f)
    lo, hi = LSQ_ORDER_RANGE
    if lo <= p < hi:
        name, note = "p", ""
    else:
        names = ("2", "12") if p >= hi else ("1", "2", "12")
        # a fixed-order fit keeps two degrees of freedom: with four grids the two-term fit
        # (three coefficients) follows the scatter and extrapolates outside the data
        names = tuple(nm for nm in names if n - 1 - len(LSQ_FITS[nm]) >= 2)
        fits = {nm: _best_fit(scale, f, LSQ_FITS[nm]) for nm in names}
        name = min(names, key=lambda nm: fits[nm][2])
        phi0, fit, sigma = fits[name]
        bound = (" (the search's bound)" if p <= LSQ_ORDER_BOUNDS[0] * 1.0001
                 or p >= LSQ_ORDER_BOUNDS[1] * 0.9999 else "")
        orders = LSQ_FITS[name]
        note = (f"free order p = {p:.2g}{bound} outside {lo}..{hi}: the fixed "
                f"order{'s' if len(orders) > 1 else ''} "
                f"{' and '.join(f'{q:g}' for q in orders)} fit best, Fs 3")
    error = np.abs(fit - phi0)
    dev = np.abs(f - fit)
    good = sigma < data_range
    fs = LSQ_SAFETY_FACTORS[0] if name == "p" and good else LSQ_SAFETY_FACTORS[1]
    if good:
        u = fs * error + sigma + dev
    else:
        u = 3.0 * sigma / data_range * (error + sigma + dev)
        note = (note + "; " if note else "") + \
            "the fit's scatter exceeds the data range: U = 3 sigma / range (error + ...)"
    return LeastSquaresStudy(tuple(h.tolist()), tuple(f.tolist()), float(p), name,
                             float(phi0), float(sigma), data_range, fs,
                             tuple(error.tolist()), tuple(u.tolist()), note)

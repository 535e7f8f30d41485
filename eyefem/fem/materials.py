"""Generalised Mooney-Rivlin materials in reduced invariants.

    W(C) = sum_{r,s} c_rs (I1bar - 3)^r (I2bar - 3)^s        [MPa]

with I1bar = J^(-2/3) I1, I2bar = J^(-4/3) I2 the reduced invariants of the right
Cauchy-Green tensor C = F^T F. Neo-Hookean is c10 only; Mooney-Rivlin is c10 and c01.
Incompressibility is enforced by the element's Lagrange multiplier, not by W.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

MAX_ORDER = 3
"""Highest power r, s of the invariant terms (a (4, 4) coefficient table)."""


@dataclasses.dataclass(frozen=True)
class MooneyRivlin:
    """A generalised Mooney-Rivlin material.

    Attributes:
      name: name used in meshes and case files.
      coeffs: (4, 4) table c[r, s] in MPa; c[0, 0] is ignored (must be 0).
    """

    name: str
    coeffs: np.ndarray

    def __post_init__(self):
        c = np.zeros((MAX_ORDER + 1, MAX_ORDER + 1))
        given = np.asarray(self.coeffs, dtype=np.float64)
        if given.ndim != 2 or given.shape[0] > MAX_ORDER + 1 or given.shape[1] > MAX_ORDER + 1:
            raise ValueError(f"material '{self.name}': coefficient table shape {given.shape}; "
                             f"r, s must be at most {MAX_ORDER}")
        c[: given.shape[0], : given.shape[1]] = given
        if not np.all(np.isfinite(c)):
            raise ValueError(f"material '{self.name}': non-finite coefficient")
        if c[0, 0] != 0.0:
            raise ValueError(f"material '{self.name}': c00 = {c[0, 0]} has no meaning; set it to 0")
        mu = 2.0 * (c[1, 0] + c[0, 1])
        if c[1, 0] < 0 or c[0, 1] < 0 or mu <= 0:
            raise ValueError(
                f"material '{self.name}': c10 = {c[1, 0]} MPa, c01 = {c[0, 1]} MPa; need c10 >= 0, "
                "c01 >= 0 and c10 + c01 > 0 (the initial shear modulus 2(c10 + c01) must be positive)")
        object.__setattr__(self, "coeffs", c)

    @property
    def shear_modulus(self) -> float:
        """Initial shear modulus mu = 2 (c10 + c01), MPa."""
        return 2.0 * (self.coeffs[1, 0] + self.coeffs[0, 1])

    @classmethod
    def from_terms(cls, name: str, terms: dict[str, float]) -> "MooneyRivlin":
        """Build from named terms such as ``{"c10": 25.0, "c01": 5.0}`` (MPa)."""
        c = np.zeros((MAX_ORDER + 1, MAX_ORDER + 1))
        for key, val in terms.items():
            if len(key) != 3 or key[0] != "c" or not key[1:].isdigit():
                raise ValueError(f"material '{name}': unknown coefficient '{key}'; "
                                 "use c10, c01, c20, c11, c02, c30, ... (crs with r, s <= 3)")
            r, s = int(key[1]), int(key[2])
            if r > MAX_ORDER or s > MAX_ORDER:
                raise ValueError(f"material '{name}': '{key}' has r or s > {MAX_ORDER}")
            c[r, s] = float(val)
        return cls(name, c)


def neo_hookean(name: str, c10: float) -> MooneyRivlin:
    """Neo-Hookean W = c10 (I1bar - 3); shear modulus 2 c10 (MPa)."""
    return MooneyRivlin.from_terms(name, {"c10": c10})


def mooney_rivlin(name: str, c10: float, c01: float) -> MooneyRivlin:
    """Two-term Mooney-Rivlin W = c10 (I1bar - 3) + c01 (I2bar - 3) (MPa)."""
    return MooneyRivlin.from_terms(name, {"c10": c10, "c01": c01})


def strain_energy(i1b, i2b, coeffs):
    """W from reduced invariants and a (4, 4) coefficient table (broadcasting over leading axes).

    Args:
      i1b, i2b: reduced invariants, shape (...).
      coeffs: (..., 4, 4) c_rs, MPa.
    Returns:
      W, shape (...), MPa.
    """
    a = i1b - 3.0
    b = i2b - 3.0
    pa = jnp.stack([jnp.ones_like(a), a, a * a, a * a * a], axis=-1)
    pb = jnp.stack([jnp.ones_like(b), b, b * b, b * b * b], axis=-1)
    return jnp.einsum("...r,...rs,...s->...", pa, coeffs, pb)


def invariant_derivatives(i1b, i2b, coeffs):
    """dW/dI1bar and dW/dI2bar (numpy), shape (...), MPa; used by the analytic checks."""
    a = np.asarray(i1b) - 3.0
    b = np.asarray(i2b) - 3.0
    c = np.asarray(coeffs)
    pa = np.stack([np.ones_like(a), a, a * a, a ** 3], -1)
    pb = np.stack([np.ones_like(b), b, b * b, b ** 3], -1)
    dpa = np.stack([np.zeros_like(a), np.ones_like(a), 2 * a, 3 * a * a], -1)
    dpb = np.stack([np.zeros_like(b), np.ones_like(b), 2 * b, 3 * b * b], -1)
    w1 = np.einsum("...r,...rs,...s->...", dpa, c, pb)
    w2 = np.einsum("...r,...rs,...s->...", pa, c, dpb)
    return w1, w2

"""Generalised Mooney-Rivlin materials in reduced invariants.

    W(C) = sum_{r,s} c_rs (I1bar - 3)^r (I2bar - 3)^s        [MPa]

with I1bar = J^(-2/3) I1, I2bar = J^(-4/3) I2 the reduced invariants of the right
Cauchy-Green tensor C = F^T F. Neo-Hookean is c10 only; Mooney-Rivlin is c10 and c01.
Incompressibility is enforced by the element's Lagrange multiplier, not by W
(:class:`MooneyRivlin`: the default of case files and the eye).

FEBio's laws (docs/febio.md, "Materials"; FEBio's FEUncoupledMaterial, FEMooneyRivlin,
FENeoHookean, FECoupledMooneyRivlin), on the displacement-only hexahedron of
eyefem.fem.solid_compressible:

* :class:`UncoupledMooneyRivlin`: the same W plus FEBio's volumetric energy
  U(J) = k/2 (ln J)^2 with a bulk modulus k > 0 (MPa; nearly incompressible), evaluated
  on the element's volume ratio Jbar = v / V (FEBio's three-field hexahedron);
* :class:`CoupledMooneyRivlin`: W = c1 (I1 - 3) + c2 (I2 - 3) - 2 (c1 + 2 c2) ln J
  + lam/2 (ln J)^2 in the unreduced invariants, at every Gauss point: FEBio's
  "coupled Mooney-Rivlin" (lam = its k) and "neo-Hookean" (c1 = mu/2, c2 = 0, lam its
  Lame constant; :func:`febio_neo_hookean` from E and v).
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
        """Build from named terms such as ``{"c10": 25.0, "c01": 5.0}`` (MPa). A bulk
        modulus ``k`` > 0 (MPa) gives the nearly incompressible
        :class:`UncoupledMooneyRivlin`; ``k`` = 0 or absent, the exactly incompressible
        material."""
        c = np.zeros((MAX_ORDER + 1, MAX_ORDER + 1))
        k = 0.0
        for key, val in terms.items():
            if key == "k":
                k = float(val)
                continue
            if len(key) != 3 or key[0] != "c" or not key[1:].isdigit():
                raise ValueError(f"material '{name}': unknown coefficient '{key}'; "
                                 "use c10, c01, c20, c11, c02, c30, ... (crs with r, s <= 3) "
                                 "and the bulk modulus k (0 or absent: incompressible)")
            r, s = int(key[1]), int(key[2])
            if r > MAX_ORDER or s > MAX_ORDER:
                raise ValueError(f"material '{name}': '{key}' has r or s > {MAX_ORDER}")
            c[r, s] = float(val)
        if k != 0.0:
            return UncoupledMooneyRivlin(name, c, k)
        return cls(name, c)


@dataclasses.dataclass(frozen=True)
class UncoupledMooneyRivlin(MooneyRivlin):
    """FEBio's uncoupled Mooney-Rivlin: W(I1bar, I2bar) of :class:`MooneyRivlin` plus the
    volumetric energy U(J) = k/2 (ln J)^2, nearly incompressible (FEBio's default
    pressure model, FEUncoupledMaterial::U). The element evaluates U on its volume ratio
    Jbar = v / V (eyefem.fem.solid_compressible).

    Attributes: name, coeffs as :class:`MooneyRivlin`; k: bulk modulus, MPa (> 0).
    """

    k: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        k = float(self.k)
        if not (np.isfinite(k) and k > 0):
            raise ValueError(f"material '{self.name}': bulk modulus k = {self.k} MPa; need a "
                             "finite k > 0 (omit k, or give 0, for the exactly incompressible "
                             "material)")
        object.__setattr__(self, "k", k)


@dataclasses.dataclass(frozen=True)
class CoupledMooneyRivlin:
    """FEBio's coupled Mooney-Rivlin (FECoupledMooneyRivlin), in the unreduced invariants
    I1, I2 of C and J = det F:

        W = c1 (I1 - 3) + c2 (I2 - 3) - 2 (c1 + 2 c2) ln J + lam/2 (ln J)^2     [MPa]

    (stress free at F = I; initial shear modulus mu = 2 (c1 + c2), initial bulk modulus
    lam + 4/3 c1 + 16/3 c2: :attr:`bulk_modulus`). With c2 = 0 it is FEBio's "neo-Hookean"
    (FENeoHookean, W = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2 with c1 = mu / 2;
    :func:`febio_neo_hookean`). Evaluated at every Gauss point (no element multiplier).

    Attributes: name; c1, c2, lam: MPa (c1 > 0, c2 >= 0, lam >= 0: FEBio's "k" of the
      coupled Mooney-Rivlin, the Lame constant of neo-Hookean); law: the FEBio type it
      came from ("coupled Mooney-Rivlin" or "neo-Hookean"), for messages and the export.
    """

    name: str
    c1: float
    c2: float = 0.0
    lam: float = 0.0
    law: str = "coupled Mooney-Rivlin"

    def __post_init__(self):
        vals = [float(self.c1), float(self.c2), float(self.lam)]
        if not all(np.isfinite(vals)):
            raise ValueError(f"material '{self.name}': non-finite constant in c1 = {self.c1}, "
                             f"c2 = {self.c2}, lam = {self.lam} MPa")
        if vals[0] <= 0 or vals[1] < 0 or vals[2] < 0:
            raise ValueError(f"material '{self.name}' ({self.law}): c1 = {self.c1} MPa, c2 = "
                             f"{self.c2} MPa, lam = {self.lam} MPa; need c1 > 0, c2 >= 0 and "
                             "lam >= 0")
        for f, v in zip(("c1", "c2", "lam"), vals):
            object.__setattr__(self, f, v)

    @property
    def coeffs(self) -> np.ndarray:
        """No uncoupled part: a zero c_rs table (4, 4)."""
        return np.zeros((MAX_ORDER + 1, MAX_ORDER + 1))

    @property
    def shear_modulus(self) -> float:
        """Initial shear modulus mu = 2 (c1 + c2), MPa."""
        return 2.0 * (self.c1 + self.c2)

    @property
    def bulk_modulus(self) -> float:
        """Initial bulk modulus d2W/d(ln J)^2 at J = 1 along a pure dilatation,
        lam + 4/3 c1 + 16/3 c2 (neo-Hookean: lam + 2 mu / 3), MPa."""
        return self.lam + (4.0 * self.c1 + 16.0 * self.c2) / 3.0


def febio_neo_hookean(name: str, E: float, v: float) -> CoupledMooneyRivlin:
    """FEBio's compressible "neo-Hookean" from Young's modulus E (MPa) and Poisson's ratio
    v: mu = E / (2 (1 + v)), lam = v E / ((1 + v)(1 - 2 v)), c1 = mu / 2, c2 = 0."""
    E, v = float(E), float(v)
    if not (np.isfinite(E) and np.isfinite(v) and E > 0 and -1.0 < v < 0.5):
        raise ValueError(f"material '{name}' (neo-Hookean): E = {E} MPa, v = {v}; need E > 0 "
                         "and -1 < v < 0.5")
    mu = 0.5 * E / (1.0 + v)
    lam = v * E / ((1.0 + v) * (1.0 - 2.0 * v))
    if lam < 0:
        raise ValueError(f"material '{name}' (neo-Hookean): v = {v} < 0 gives a negative "
                         f"Lame constant ({lam:g} MPa); eyefem needs 0 <= v < 0.5")
    return CoupledMooneyRivlin(name, mu / 2.0, 0.0, lam, law="neo-Hookean")


def bulk_modulus(mat) -> float:
    """The uncoupled bulk modulus k of a material (MPa): 0 for the exactly incompressible
    :class:`MooneyRivlin` and for :class:`CoupledMooneyRivlin` (whose volumetric energy is
    part of W)."""
    return float(getattr(mat, "k", 0.0)) if isinstance(mat, UncoupledMooneyRivlin) else 0.0


def coupled_constants(mat) -> np.ndarray:
    """(c1, c2, lam) of a :class:`CoupledMooneyRivlin`, zeros (3,) for other materials, MPa."""
    if isinstance(mat, CoupledMooneyRivlin):
        return np.array([mat.c1, mat.c2, mat.lam])
    return np.zeros(3)


def is_compressible(mat) -> bool:
    """True for the materials with a volumetric energy (no element multiplier):
    :class:`UncoupledMooneyRivlin` and :class:`CoupledMooneyRivlin`."""
    return isinstance(mat, (UncoupledMooneyRivlin, CoupledMooneyRivlin))


def volumetric_energy(J, k):
    """FEBio's U(J) = k/2 (ln J)^2, MPa (broadcasting)."""
    lj = jnp.log(J)
    return 0.5 * k * lj * lj


def coupled_energy(i1, i2, J, cc):
    """W of :class:`CoupledMooneyRivlin` from I1, I2, J (...) and (..., 3) constants
    (c1, c2, lam), MPa."""
    c1, c2, lam = cc[..., 0], cc[..., 1], cc[..., 2]
    lj = jnp.log(J)
    return c1 * (i1 - 3.0) + c2 * (i2 - 3.0) - 2.0 * (c1 + 2.0 * c2) * lj + 0.5 * lam * lj * lj


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

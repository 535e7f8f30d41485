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
  Lame constant; :func:`febio_neo_hookean` from E and v);
* :class:`FebioLaw`: FEBio's further laws (:data:`FEBIO_LAWS`: Ogden, Holmes-Mow, trans
  iso Mooney-Rivlin, orthotropic, ...) and their solid mixtures, on
  eyefem.fem.solid_compressible.SolidFebioLaw.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
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


# --- FEBio's further hyperelastic laws ------------------------------------------------
# Each law is a strain energy density of the deformation gradient (JAX, float64): the
# uncoupled ones of the distortional part Fbar = J^(-1/3) F (FEBio's
# DevStrainEnergyDensity), the coupled ones of F itself (StrainEnergyDensity). A material
# (:class:`FebioLaw`) is a sum of such parts, FEBio's solid mixture (FEElasticMixture,
# FEUncoupledElasticMixture: the constituents' energies add, weights 1), plus FEBio's
# U(J) = k/2 (ln J)^2 on the element's volume ratio where it is uncoupled.



def _spectral_f(lam, p, kind: int):
    """f(lam), f'(lam), f''(lam) of an eigenvalue lam of C: kind 0, lam^p (a power of the
    stretches: tr C^p = sum lam_i^p); kind 1, (ln lam)^2 / 4 (the Hencky strain's square,
    (ln stretch)^2)."""
    if kind == 0:
        return lam ** p, p * lam ** (p - 1.0), p * (p - 1.0) * lam ** (p - 2.0)
    ll = jnp.log(lam)
    return 0.25 * ll * ll, 0.5 * ll / lam, 0.5 * (1.0 - ll) / (lam * lam)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _spectral_derivative(C, p, kind):
    """The matrix function f'(C) = V diag(f'(lam)) V^T (3, 3) of a symmetric positive C,
    differentiable at repeated eigenvalues (its derivative: Daleckii-Krein, below)."""
    lam, V = jnp.linalg.eigh(C)
    return (V * _spectral_f(lam, p, kind)[1]) @ V.T


@_spectral_derivative.defjvp
def _spectral_derivative_jvp(kind, primals, tangents):
    C, p = primals
    dC = tangents[0]
    lam, V = jnp.linalg.eigh(C)
    _, f1, f2 = _spectral_f(lam, p, kind)
    dl = lam[:, None] - lam[None, :]
    close = jnp.abs(dl) <= 1e-8 * jnp.max(jnp.abs(lam))
    G = jnp.where(close, 0.5 * (f2[:, None] + f2[None, :]),
                  (f1[:, None] - f1[None, :]) / jnp.where(close, 1.0, dl))
    out = (V @ (G * (V.T @ dC @ V)) @ V.T)
    return (V * f1) @ V.T, 0.5 * (out + out.T)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def spectral_sum(C, p, kind):
    """sum_i f(lam_i) over the eigenvalues lam_i of a symmetric positive C (3, 3)
    (:func:`_spectral_f`), with the derivatives of the matrix function (exact at repeated
    eigenvalues, where an eigen-decomposition's own derivative is not defined): the
    gradient is f'(C), its derivative the Daleckii-Krein form. Used by the Ogden and Hencky
    laws (FEBio evaluates them on the eigenvalues of b)."""
    lam = jnp.linalg.eigvalsh(C)
    return jnp.sum(_spectral_f(lam, p, kind)[0])


@spectral_sum.defjvp
def _spectral_sum_jvp(kind, primals, tangents):
    C, p = primals
    dC = tangents[0]
    G = _spectral_derivative(C, p, kind)
    return spectral_sum(C, p, kind), jnp.sum(G * dC)


def _invariants(F):
    C = F.T @ F
    i1 = jnp.trace(C)
    i2 = 0.5 * (i1 * i1 - jnp.sum(C * C))
    return C, i1, i2


def _fiber_exp_linear(lam, c3, c4, c5, lam1):
    """FEBio's fiber-exp-linear energy of a fibre stretch lam (FEFiberExpLinear,
    FEFiberExpLinearUC): 0 for lam < 1; c3 e^-c4 (Ei(c4 lam) - Ei(c4)) - c3 ln lam up to
    lam1; then linear in the stress, c5 (lam - lam1) + c6 ln(lam / lam1) + W(lam1), c6 =
    c3 (e^(c4 (lam1 - 1)) - 1) - c5 lam1; c3 = 0 means c3 = c5 / c4 e^(-c4 (lam1 - 1))
    (the stresses join at lam1)."""
    from jax.scipy.special import expi
    c3 = jnp.where(c3 == 0, c5 / c4 * jnp.exp(-c4 * (lam1 - 1.0)), c3)
    on = lam >= 1.0
    lt = jnp.where(on, lam, 1.0)
    low = jnp.minimum(lt, lam1)
    w = c3 * jnp.exp(-c4) * (expi(c4 * low) - expi(c4)) - c3 * jnp.log(low)
    c6 = c3 * (jnp.exp(c4 * (lam1 - 1.0)) - 1.0) - c5 * lam1
    hi = jnp.maximum(lt, lam1)
    w = w + jnp.where(lt > lam1, c5 * (hi - lam1) + c6 * jnp.log(hi / lam1), 0.0)
    return jnp.where(on, w, 0.0)


def _fiber_stretch(F, a0):
    a = F @ a0
    return jnp.sqrt(jnp.dot(a, a))


def _w_ogden(F, c, a0):  # c: (c1..c6, m1..m6); F is Fbar (uncoupled)
    C = F.T @ F
    return sum(jnp.where(c[j] == 0, 0.0, c[j] / c[6 + j] ** 2
                         * (spectral_sum(C, 0.5 * c[6 + j], 0) - 3.0)) for j in range(6))


def _w_ogden_unconstrained(F, c, a0):  # c: (cp, c1..c6, m1..m6)
    C = F.T @ F
    lj = jnp.log(jnp.linalg.det(F))
    J = jnp.exp(lj)
    w = 0.5 * c[0] * (J - 1.0) ** 2
    return w + sum(jnp.where(c[1 + j] == 0, 0.0, c[1 + j] / c[7 + j] ** 2
                             * (spectral_sum(C, 0.5 * c[7 + j], 0) - 3.0 - c[7 + j] * lj))
                   for j in range(6))


def _lame(E, v):
    return v * E / ((1.0 + v) * (1.0 - 2.0 * v)), 0.5 * E / (1.0 + v)


def _w_isotropic_elastic(F, c, a0):  # c: (E, v); St Venant-Kirchhoff
    lam, mu = _lame(c[0], c[1])
    E = 0.5 * (F.T @ F - jnp.eye(3))
    tr = jnp.trace(E)
    return 0.5 * lam * tr * tr + mu * jnp.sum(E * E)


def _w_hencky(F, c, a0):  # c: (E, v)
    lam, mu = _lame(c[0], c[1])
    lj = jnp.log(jnp.linalg.det(F))
    return 0.5 * lam * lj * lj + mu * spectral_sum(F.T @ F, 0.0, 1)


def _w_holmes_mow(F, c, a0):  # c: (E, v, beta)
    lam, mu = _lame(c[0], c[1])
    ha = lam + 2.0 * mu
    _, i1, i2 = _invariants(F)
    i3 = jnp.linalg.det(F) ** 2
    eq = jnp.exp(c[2] * ((2.0 * mu - lam) * (i1 - 3.0) + lam * (i2 - 3.0)) / ha) / i3 ** c[2]
    return ha / (4.0 * c[2]) * (eq - 1.0)


def _w_holmes_mow_uc(F, c, a0):  # c: (mu, beta)
    _, i1, _ = _invariants(F)
    return c[0] / (2.0 * c[1]) * (jnp.exp(c[1] * (i1 - 3.0)) - 1.0)


def _w_arruda_boyce(F, c, a0):  # c: (mu, N)
    _, i1, _ = _invariants(F)
    a = (0.5, 0.1, 11.0 / 350.0, 19.0 / 1750.0, 519.0 / 134750.0)
    return c[0] * sum(a[i] * (i1 ** (i + 1) - 3.0 ** (i + 1)) / c[1] ** i for i in range(5))


def _w_veronda_westmann(F, c, a0):  # c: (c1, c2)
    _, i1, i2 = _invariants(F)
    return c[0] * (jnp.exp(c[1] * (i1 - 3.0)) - 1.0) - 0.5 * c[0] * c[1] * (i2 - 3.0)


def _w_yeoh(F, c, a0):  # c: (c1..c6)
    _, i1, _ = _invariants(F)
    return sum(c[i] * (i1 - 3.0) ** (i + 1) for i in range(6))


def _w_mooney_rivlin(F, c, a0):  # c: (c1, c2), F = Fbar
    _, i1, i2 = _invariants(F)
    return c[0] * (i1 - 3.0) + c[1] * (i2 - 3.0)


def _w_neo_hookean(F, c, a0):  # c: (E, v), coupled
    lam, mu = _lame(c[0], c[1])
    _, i1, _ = _invariants(F)
    lj = jnp.log(jnp.linalg.det(F))
    return 0.5 * mu * (i1 - 3.0) - mu * lj + 0.5 * lam * lj * lj


def _w_coupled_mooney_rivlin(F, c, a0):  # c: (c1, c2, k)
    _, i1, i2 = _invariants(F)
    lj = jnp.log(jnp.linalg.det(F))
    return (c[0] * (i1 - 3.0) + c[1] * (i2 - 3.0) - 2.0 * (c[0] + 2.0 * c[1]) * lj
            + 0.5 * c[2] * lj * lj)


def _w_tiso_mooney_rivlin(F, c, a0):  # c: (c1, c2, c3, c4, c5, lam_max), F = Fbar
    return _w_mooney_rivlin(F, c[:2], a0) + _fiber_exp_linear(
        _fiber_stretch(F, a0), c[2], c[3], c[4], c[5])


def _w_tiso_veronda_westmann(F, c, a0):  # c: (c1, c2, c3, c4, c5, lam_max), F = Fbar
    return _w_veronda_westmann(F, c[:2], a0) + _fiber_exp_linear(
        _fiber_stretch(F, a0), c[2], c[3], c[4], c[5])


def _w_fiber_exp_linear(F, c, a0):  # c: (c3, c4, c5, lambda); F or Fbar
    return _fiber_exp_linear(_fiber_stretch(F, a0), c[0], c[1], c[2], c[3])


def _ortho_lame(c):
    """FEBio's orthotropic Lame constants (FEOrthoElastic::EvaluateLameCoefficients,
    FEFungOrthotropic::Validate) from c = (E1, E2, E3, G12, G23, G31, v12, v23, v31):
    mu (3,), lam (3, 3), MPa."""
    E1, E2, E3, G12, G23, G31, v12, v23, v31 = (c[i] for i in range(9))
    mu = jnp.stack([G12 + G31 - G23, G12 - G31 + G23, -G12 + G31 + G23])
    comp = jnp.array([[1.0 / E1, -v12 / E1, -v31 / E3],
                      [-v12 / E1, 1.0 / E2, -v23 / E2],
                      [-v31 / E3, -v23 / E2, 1.0 / E3]])
    stiff = jnp.linalg.inv(comp)
    return mu, stiff - 2.0 * jnp.diag(mu)


def _ortho_quadratic(E, c, axes):
    """sum_i mu_i A_i : E^2 + 1/2 sum_ij lam_ij (A_i : E)(A_j : E), A_i = a_i a_i (the
    material axes, rows of ``axes`` (3, 3))."""
    mu, lam = _ortho_lame(c)
    ae = jnp.einsum("ai,ij,aj->a", axes, E, axes)
    ae2 = jnp.einsum("ai,ij,aj->a", axes, E @ E, axes)
    return jnp.dot(mu, ae2) + 0.5 * ae @ lam @ ae


def _w_ortho_elastic(F, c, axes):  # c: (E1, E2, E3, G12, G23, G31, v12, v23, v31)
    return _ortho_quadratic(0.5 * (F.T @ F - jnp.eye(3)), c, axes)


def _w_fung_ortho(F, c, axes):  # c: the nine above and c; F = Fbar
    q = 2.0 * _ortho_quadratic(0.5 * (F.T @ F - jnp.eye(3)), c, axes)
    return 0.5 * c[9] * (jnp.exp(q / c[9]) - 1.0)


def _w_fung_ortho_compressible(F, c, axes):  # c: the nine, c, k
    lj = jnp.log(jnp.linalg.det(F))
    return _w_fung_ortho(F, c, axes) + 0.5 * c[10] * lj * lj


def _w_active_isotropic(F, c, a0):  # c: (T0,); S = T0 I
    _, i1, _ = _invariants(F)
    return 0.5 * c[0] * (i1 - 3.0)


def _w_active_uniaxial(F, c, axes):  # c: (T0,); S = T0 n0 n0, n0 the first axis
    n = F @ axes[0]
    return 0.5 * c[0] * (jnp.dot(n, n) - 1.0)


def _w_active_trans_iso(F, c, axes):  # c: (T0,); S = T0 (I - n0 n0)
    return _w_active_isotropic(F, c, None) - _w_active_uniaxial(F, c, axes)


_ORTHO = (("E1", None), ("E2", None), ("E3", None), ("G12", None), ("G23", None),
          ("G31", None), ("v12", None), ("v23", None), ("v31", None))

FEBIO_LAWS = {
    # FEBio type (lower case): (energy, uncoupled, parameters (name, default), fibre)
    "ogden": (_w_ogden, True, tuple((f"c{i}", 0.0) for i in range(1, 7))
              + tuple((f"m{i}", 1.0) for i in range(1, 7)), False),
    "ogden unconstrained": (_w_ogden_unconstrained, False, (("cp", 0.0),) + tuple(
        (f"c{i}", 0.0) for i in range(1, 7)) + tuple((f"m{i}", 1.0) for i in range(1, 7)),
        False),
    "isotropic elastic": (_w_isotropic_elastic, False, (("E", None), ("v", None)), False),
    "isotropic hencky": (_w_hencky, False, (("E", None), ("v", None)), False),
    "holmes-mow": (_w_holmes_mow, False, (("E", None), ("v", None), ("beta", None)), False),
    "uncoupled holmes-mow": (_w_holmes_mow_uc, True, (("mu", None), ("beta", None)), False),
    "arruda-boyce": (_w_arruda_boyce, True, (("mu", None), ("N", None)), False),
    "veronda-westmann": (_w_veronda_westmann, True, (("c1", None), ("c2", None)), False),
    "yeoh": (_w_yeoh, True, tuple((f"c{i}", 0.0) for i in range(1, 7)), False),
    "mooney-rivlin": (_w_mooney_rivlin, True, (("c1", None), ("c2", 0.0)), False),
    "neo-hookean": (_w_neo_hookean, False, (("E", None), ("v", None)), False),
    "coupled mooney-rivlin": (_w_coupled_mooney_rivlin, False,
                              (("c1", None), ("c2", 0.0), ("k", None)), False),
    "trans iso mooney-rivlin": (_w_tiso_mooney_rivlin, True, (
        ("c1", None), ("c2", 0.0), ("c3", None), ("c4", None), ("c5", None),
        ("lam_max", None)), True),
    "trans iso veronda-westmann": (_w_tiso_veronda_westmann, True, (
        ("c1", None), ("c2", None), ("c3", None), ("c4", None), ("c5", None),
        ("lam_max", None)), True),
    "fiber-exp-linear": (_w_fiber_exp_linear, False, (
        ("c3", 0.0), ("c4", 0.0), ("c5", 0.0), ("lambda", 1.0)), True),
    "uncoupled fiber-exp-linear": (_w_fiber_exp_linear, True, (
        ("c3", 0.0), ("c4", 0.0), ("c5", 0.0), ("lambda", 1.0)), True),
    "orthotropic elastic": (_w_ortho_elastic, False, _ORTHO, 3),
    # FEBio's prescribed active contractions: Cauchy stresses T0 b / J, T0 F n0 n0 F^T / J,
    # T0 (b - F n0 n0 F^T) / J, the "uncoupled" versions the same (their DevStress is not
    # deviatoric): the energies T0/2 (I1 - 3), T0/2 (I4 - 1), T0/2 (I1 - I4 - 2) of F
    "prescribed isotropic active contraction": (_w_active_isotropic, False, (("T0", 0.0),), 0),
    "uncoupled prescribed isotropic active contraction": (_w_active_isotropic, False,
                                                          (("T0", 0.0),), 0),
    "prescribed uniaxial active contraction": (_w_active_uniaxial, False, (("T0", 0.0),), 3),
    "uncoupled prescribed uniaxial active contraction": (_w_active_uniaxial, False,
                                                         (("T0", 0.0),), 3),
    "prescribed trans iso active contraction": (_w_active_trans_iso, False, (("T0", 0.0),), 3),
    "uncoupled prescribed trans iso active contraction": (_w_active_trans_iso, False,
                                                          (("T0", 0.0),), 3),
    "fung orthotropic": (_w_fung_ortho, True, _ORTHO + (("c", None),), 3),
    "fung-ortho-compressible": (_w_fung_ortho_compressible, False,
                                _ORTHO + (("c", None), ("k", None)), 3),
}
"""FEBio's hyperelastic laws read through :class:`FebioLaw` (FEBio type, lower case ->
(energy w(F, constants (m,), fibre direction (3,) or material axes (3, 3)) in MPa,
uncoupled (w of Fbar), the parameters in order with FEBio's defaults (None: required),
the directions it needs: 0, 1 (a fibre) or 3 (the material axes, rows))),
as FEBio's sources define them: FEOgdenMaterial, FEOgdenUnconstrained, FEIsotropicElastic
(St Venant-Kirchhoff), FEIsoHencky, FEHolmesMow, FEHolmesMowUC, FEArrudaBoyce (the
five-term series), FEVerondaWestmann, FEYeoh, FEMooneyRivlin, FENeoHookean,
FECoupledMooneyRivlin, FETransIsoMooneyRivlin and FETransIsoVerondaWestmann (with
FEFiberExpLinearUC), FEFiberExpLinear, FEUncoupledFiberExpLinear, FEOrthoElastic,
FEFungOrthotropic (of Cbar), FEFungOrthoCompressible, and
FEPrescribedActiveContraction{Isotropic,Uniaxial,TransIso} with their UC versions."""


@dataclasses.dataclass(frozen=True)
class FebioLaw:
    """One of FEBio's hyperelastic materials of :data:`FEBIO_LAWS`, or their solid
    mixture: W = sum over the parts of w_i (Fbar for an uncoupled part, F for a coupled
    one), MPa, plus U(J) = k/2 (ln J)^2 (FEBio's default pressure model) on the element's
    volume ratio where the material is uncoupled (eyefem.fem.solid_compressible.
    SolidFebioLaw).

    Attributes:
      name: the material's name.
      law: FEBio's type (e.g. "Ogden", "solid mixture"), for messages.
      parts: ((FEBio type lower case, constants (m,)), ...), one per constituent.
      uncoupled: True for FEBio's uncoupled materials (k > 0 required).
      k: bulk modulus of U, MPa (0 for a coupled material).
      fibers: for each part with a fibre, how its direction is given (the reader's
        description; the directions themselves are the term's data), else None.
      curves: ((index into :meth:`constants`, FEBio load controller id), ...): constants
        on a load curve (FEBio multiplies the given value by the curve's; the reader sets
        them per step).
    """

    name: str
    law: str
    parts: tuple
    uncoupled: bool
    k: float = 0.0
    fibers: tuple = ()
    curves: tuple = ()

    def __post_init__(self):
        for kind, consts in self.parts:
            if kind not in FEBIO_LAWS:
                raise ValueError(f"material '{self.name}': law '{kind}' is not one of "
                                 f"{sorted(FEBIO_LAWS)}")
            if not np.all(np.isfinite(np.asarray(consts, np.float64))):
                raise ValueError(f"material '{self.name}' ({kind}): non-finite constant in "
                                 f"{tuple(consts)}")
        if self.uncoupled and not (np.isfinite(self.k) and self.k > 0):
            raise ValueError(f"material '{self.name}' ({self.law}): bulk modulus k = "
                             f"{self.k} MPa; an uncoupled material needs k > 0")
        object.__setattr__(self, "parts", tuple(
            (kind, tuple(float(x) for x in consts)) for kind, consts in self.parts))

    @property
    def coeffs(self) -> np.ndarray:
        """No Mooney-Rivlin table: zeros (4, 4) (the Q1P0 element is not used)."""
        return np.zeros((MAX_ORDER + 1, MAX_ORDER + 1))

    @property
    def n_fibers(self) -> int:
        """Directions the law needs at a point: a fibre per fibred part, three material
        axes per orthotropic part."""
        return sum(int(FEBIO_LAWS[kind][3]) for kind, _ in self.parts)

    def structure(self) -> tuple:
        """The law's shape, for the compiled kernels: ((type, n constants, n directions),
        ...)."""
        return tuple((kind, len(c), int(FEBIO_LAWS[kind][3])) for kind, c in self.parts)

    def constants(self) -> np.ndarray:
        """All parts' constants in order, (m,)."""
        return np.array([x for _, c in self.parts for x in c], np.float64)


def febio_law_energy(structure: tuple, F, consts, a0):
    """W (MPa) of a law of :meth:`FebioLaw.structure` at one point: F (3, 3), its
    constants (m,) (:meth:`FebioLaw.constants`), its directions a0 (n_fibers, 3) (unit,
    reference configuration: the fibres, the material axes)."""
    J = jnp.linalg.det(F)
    Fbar = J ** (-1.0 / 3.0) * F
    w, at, fi = 0.0, 0, 0
    for kind, m, nd in structure:
        fn, uncoupled = FEBIO_LAWS[kind][:2]
        d = a0[fi] if nd == 1 else (a0[fi:fi + 3] if nd == 3 else None)
        w = w + fn(Fbar if uncoupled else F, consts[at:at + m], d)
        at += m
        fi += nd
    return w

"""The time-dependent sclera and cornea: the case parameters of the wall's relaxation
(issue 74, item 3) and the Prony constants they give the solid
(:class:`eyefem.fem.viscoelastic.ViscoelasticQ1P0`).

The law is quasi-linear viscoelastic: the tissue's elastic law (its preset, e.g. the
``physiological`` eye calibrated to living eyes' fast injections) is the instantaneous
response, and its isochoric stress relaxes with the reduced relaxation function

    G(t) = g_inf + sum_i g_i exp(-t / tau_i),     g_inf = 1 - sum_i g_i,

so that a load held long after the last tau_i meets the elastic law scaled by g_inf (the
relaxed modulus). The same (g_i, tau_i) apply to every relaxing tissue
(``relaxation_tissues``, the corneoscleral wall by default); the other tissues stay
elastic. Times are minutes (the timeline's clock).

**Published constants.** None ship: no scleral or corneal relaxation curve or table of
Prony (or QLV) constants could be read, and none are invented. The stored copies of
the candidate papers hold their abstracts or openings only:

- Downs et al., J Biomech Eng 125:124 (2003), pmc.ncbi.nlm.nih.gov/articles/PMC2744140:
  uniaxial stress relaxation of rabbit and monkey peripapillary sclera at 0-1 % strain,
  a spectral (Fung) reduced relaxation function; the monkey's is stiffer at once and at
  equilibrium and relaxes more slowly. Its table of (C, tau1, tau2) and moduli: not read.
- Downs et al., IOVS 46:540 (2005), iovs.arvojournals.org/article.aspx?articleid=2123970:
  monkey, normal against early glaucoma; no constants in the stored text.
- Cruz Perez, Morris, Hart, Liu, J Biomed Sci Eng 6:29 (2013), scirp.org/html/40830.html:
  an FE eye with viscoelastic cornea and sclera; its moduli and time constants: not read.
- Song, Lim, Park, Demer, J Biomech 2023, 111530: tensile creep of human sclera over
  1,500 s, Prony series; no constants in the abstract.
- Hatami-Marbini, Vision 9:1 (2025): stress relaxation of porcine posterior sclera at four
  hydrations (a logarithmic fit); no constants in the abstract.
- "Regional variation in the biomechanical properties of the human sclera" (Elsheikh et
  al., Exp Eye Res 2010; 36 donors, strips): stress 157-203 % and tangent modulus
  30.3-38.8 % higher at 200 than at 8 %/min; Whitford et al., Biomech Model Mechanobiol
  17:19 (2018): the human cornea's stiffness parallel to the lamellae about doubles from
  0.5 to 5 %/min. Rate sensitivities of a ramp, not a relaxation function.

``tissue_relaxation = "custom"`` takes constants the user supplies (from such a paper's
table, or ``benchmarks/fit_prony.py`` run on a digitised curve);
``cases/surgery/timeline_case1_relaxing.toml`` runs case 1 with illustrative ones. What a
relaxation test identifies, and what it does not (relaxation slower than the test, which
the shape at three months depends on): docs/formulation.md, "Quasi-linear viscoelastic
tissue"; docs/validation.md, "The time-dependent wall".
"""

from __future__ import annotations

import dataclasses

import numpy as np

from eyefem.io.casefile import Field

RELAXATION_MODES = ("none", "custom")
"""``tissue_relaxation``: 'none' (elastic tissues), 'custom' (the case's relaxation_g and
relaxation_tau_min). A published fitted set would be a further name here."""

WALL_TISSUES = ("sclera", "limbus", "cornea")
"""The tissues that relax by default: the corneoscleral wall, which carries the load."""

MAX_TERMS = 8


@dataclasses.dataclass(frozen=True)
class Relaxation:
    """Prony constants of the relaxing tissues.

    Attributes:
      g: fractions g_i (n,), each >= 0, sum < 1.
      tau_min: time constants tau_i (n,), minutes, > 0.
      tissues: the tissues (mesh materials) that relax; the others are elastic.
      source: where the constants come from (a paper and figure, or 'user').
    """

    g: tuple[float, ...]
    tau_min: tuple[float, ...]
    tissues: tuple[str, ...] = WALL_TISSUES
    source: str = "user"

    def __post_init__(self):
        g = tuple(float(x) for x in self.g)
        tau = tuple(float(x) for x in self.tau_min)
        object.__setattr__(self, "g", g)
        object.__setattr__(self, "tau_min", tau)
        object.__setattr__(self, "tissues", tuple(self.tissues))
        check_constants(g, tau)
        if not self.tissues:
            raise ValueError("relaxation_tissues is empty; name the tissues that relax, e.g. "
                             f"{list(WALL_TISSUES)}")

    @property
    def g_inf(self) -> float:
        """The relaxed fraction 1 - sum g_i (the equilibrium modulus over the instantaneous)."""
        return 1.0 - sum(self.g)

    def prony(self) -> dict[str, tuple[tuple[float, ...], tuple[float, ...]]]:
        """Tissue -> (g, tau_min): the ``prony`` argument of
        :func:`eyefem.solve.model.solid_model` and :func:`eyefem.solve.model.with_viscoelastic`."""
        return {t: (self.g, self.tau_min) for t in self.tissues}


PUBLISHED: dict[str, Relaxation] = {}
"""Named fitted sets (tissue_relaxation = name): none yet (module docstring)."""


def check_constants(g, tau_min, where: str = "relaxation_g / relaxation_tau_min"):
    """ValueError naming the fields and the fix unless g (n,) and tau_min (n,) are Prony
    constants: 1 to MAX_TERMS terms, g_i >= 0 with sum < 1, tau_i > 0 minutes."""
    g, tau = list(g), list(tau_min)
    if not 1 <= len(g) <= MAX_TERMS or len(g) != len(tau):
        raise ValueError(f"{where}: {len(g)} fractions and {len(tau)} time constants; give "
                         f"as many of each, 1 to {MAX_TERMS}, e.g. relaxation_g = [0.2, 0.3], "
                         "relaxation_tau_min = [10.0, 1000.0]")
    if not all(np.isfinite(g)) or min(g) < 0 or sum(g) >= 1:
        raise ValueError(f"{where}: relaxation_g = {g}; each fraction must be >= 0 and their "
                         "sum below 1 (1 - sum g_i is the relaxed fraction of the modulus)")
    if not all(np.isfinite(tau)) or min(tau) <= 0:
        raise ValueError(f"{where}: relaxation_tau_min = {tau}; each time constant must be "
                         "above 0 minutes")


def _numbers(v) -> bool:
    return isinstance(v, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                       for x in v)


RELAXATION_FIELDS = [
    Field("tissue_relaxation", str, "none",
          "time-dependent sclera and cornea: 'none' (elastic tissues, the same response at "
          "every time) or 'custom' (quasi-linear viscoelastic: the preset's elastic law is the "
          "instantaneous response and relaxes as G(t) = 1 - sum g_i + sum g_i exp(-t / "
          "tau_i) with relaxation_g and relaxation_tau_min; the relaxed modulus is 1 - sum "
          "g_i times the elastic one). No published fitted set ships: no scleral relaxation "
          "curve could be read (eyefem/eye/relaxation.py, docs/formulation.md); time passes "
          "only on the timeline (volume_regulation = true)",
          lambda v: v in RELAXATION_MODES or v in PUBLISHED,
          f"one of {list(RELAXATION_MODES) + sorted(PUBLISHED)}"),
    Field("relaxation_g", list, [],
          "Prony fractions g_i of tissue_relaxation = 'custom', dimensionless, each >= 0, sum "
          "below 1 (e.g. [0.2, 0.3]); from a published relaxation test or benchmarks/"
          "fit_prony.py", _numbers, "a list of numbers"),
    Field("relaxation_tau_min", list, [],
          "Prony time constants tau_i of tissue_relaxation = 'custom', minutes, > 0, one per "
          "fraction (e.g. [10.0, 1000.0]); a creep or relaxation test of T minutes identifies "
          "those below about T only", _numbers, "a list of numbers"),
    Field("relaxation_tissues", list, list(WALL_TISSUES),
          "the tissues that relax (mesh materials); the others stay elastic",
          lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v) and len(v) > 0,
          "a non-empty list of tissue names"),
]
"""The relaxation's case parameters (to be appended to the surgery schema)."""


def relaxation(p: dict) -> Relaxation | None:
    """The Relaxation of the case parameters ``p`` (RELAXATION_FIELDS), or None for
    ``tissue_relaxation = 'none'`` (or absent). ValueError naming the field otherwise."""
    mode = p.get("tissue_relaxation", "none")
    if mode == "none":
        return None
    tissues = tuple(p.get("relaxation_tissues", WALL_TISSUES))
    if mode in PUBLISHED:
        return dataclasses.replace(PUBLISHED[mode], tissues=tissues)
    if mode != "custom":
        raise ValueError(f"tissue_relaxation = {mode!r}; choose one of "
                         f"{list(RELAXATION_MODES) + sorted(PUBLISHED)}")
    g, tau = p.get("relaxation_g", []), p.get("relaxation_tau_min", [])
    if not g:
        raise ValueError("tissue_relaxation = 'custom' needs relaxation_g and "
                         "relaxation_tau_min (fractions and minutes), e.g. relaxation_g = "
                         "[0.2, 0.3], relaxation_tau_min = [10.0, 1000.0]")
    return Relaxation(tuple(g), tuple(tau), tissues, "user (case file)")


def with_relaxation(model, p: dict, name: str = "solid"):
    """The model with its solid term ``name`` relaxing as the case parameters say
    (:func:`eyefem.solve.model.with_viscoelastic`); the model itself for 'none'.
    ValueError naming the tissue when a relaxing tissue is not in the mesh, and for a
    solid of another element (``wall_element = 'ans'``, a deformable band's shortened
    loop). The surgery applies it to the model it has built, after the buckle body's
    changes (the rigid buckle leaves the solid a Q1P0 term)."""
    from eyefem.solve.model import with_viscoelastic

    rel = relaxation(p)
    if rel is None:
        return model
    missing = [t for t in rel.tissues if t not in model.mesh.materials]
    if missing:
        raise ValueError(f"relaxation_tissues: {missing} are not tissues of the mesh; it has "
                         f"{list(model.mesh.materials)}")
    return with_viscoelastic(model, rel.prony(), name)

"""Material presets of the eye model's tissues: ``seed`` and ``physiological``.

Each preset maps a tissue (a material of the eye mesh) to generalised Mooney-Rivlin
terms c_rs, MPa (eyefem.fem.materials):

- ``seed``: the seed's neo-Hookean constants (seed 6.1; the limbus the mean of cornea
  and sclera). The seed's surgical cases 1-6 use them. With them the model eye is far
  more compliant than living eyes (docs/validation.md).
- ``physiological``: strain-stiffening sclera, limbus and cornea,
  W = c10 (I1bar - 3) + c30 (I1bar - 3)^3, fitted by ``python -m optimize.calibrate``
  so that the model eye's pressure-volume response at 15 mmHg matches the ocular
  rigidity of living human eyes, K = 0.0126 per uL in P = P0 exp(K dV) (Pallikaris et
  al. 2005, IOVS 46:409). Only the wall as a whole is identified by a pressure-volume
  curve: the cornea and limbus keep the seed's ratios to the sclera (0.4 and 0.7), the
  other tissues the seed's constants (docs/validation.md).
"""

from __future__ import annotations

from eyefem.fem.materials import MooneyRivlin

SEED_MATERIALS = {  # neo-Hookean c (MPa), seed 6.1; limbus: mean of cornea and sclera
    "cornea": 0.0333, "limbus": 0.0583, "sclera": 0.0833, "ciliary_body": 0.01,
    "choroid": 0.0083, "retina": 0.0008, "optic_nerve": 0.05, "lens": 10.0}

WALL_RATIOS = {"sclera": 1.0, "limbus": 0.0583 / 0.0833, "cornea": 0.0333 / 0.0833}
"""Corneoscleral tissues whose constants the calibration scales together: ratio of each
tissue's constants to the sclera's (the seed's ratios)."""

PHYSIOLOGICAL_SCLERA = {"c10": 0.4132, "c30": 6.330e4}
"""Fitted sclera terms c_rs, MPa (python -m optimize.calibrate on the coarse eye: c10 =
0.41318, c30 = 63297; docs/validation.md). c30 is large because the wall's strains are
small: I1bar - 3 ~ 12 e^2 is of order 1e-4 to 1e-3 for membrane strains e under 1%."""

PRESETS = ("seed", "physiological")


def wall_terms(sclera: dict[str, float]) -> dict[str, dict[str, float]]:
    """Terms of the corneoscleral tissues from the sclera's terms (MPa) by WALL_RATIOS."""
    return {t: {k: r * v for k, v in sclera.items()} for t, r in WALL_RATIOS.items()}


def preset_terms(name: str) -> dict[str, dict[str, float]]:
    """Tissue -> {term: c_rs, MPa} of the preset ``name`` (one of PRESETS)."""
    if name not in PRESETS:
        raise ValueError(f"material preset '{name}' is unknown; choose one of {list(PRESETS)} "
                         "(case field materials_preset, or eyefem run --materials)")
    out = {t: {"c10": c} for t, c in SEED_MATERIALS.items()}
    if name == "physiological":
        out.update(wall_terms(PHYSIOLOGICAL_SCLERA))
    return out


def preset_materials(name: str) -> dict[str, MooneyRivlin]:
    """Tissue -> MooneyRivlin of the preset ``name``."""
    return {t: MooneyRivlin.from_terms(t, terms) for t, terms in preset_terms(name).items()}


def with_overrides(preset: str, materials: dict | None, log=None) -> dict[str, MooneyRivlin]:
    """The preset's tissues with a case's [materials] tables applied on top; each table
    that replaces a tissue of a preset other than the seed's is said on ``log``
    (a calibrated tissue silently restated as a seed table is the likely mistake)."""
    out = preset_materials(preset)
    replaced = sorted(t for t in (materials or {}) if t in out)
    if replaced and preset != "seed" and log is not None:
        log.warning("the case file's [materials] tables of %s replace the '%s' preset's "
                    "constants of those tissues (drop the tables to use the preset)",
                    ", ".join(replaced), preset)
    return {**out, **(materials or {})}


def tissues_replaced(materials: dict, preset: str) -> tuple[dict, list[str]]:
    """A case's [materials] tables without those of the tissues the preset ``preset``
    defines: (the tables kept, the tissue names dropped). For a preset named on the
    command line (``eyefem run --materials``), which must win over a case file that
    restates another preset's constants as tables (cases 1-6 restate the seed's)."""
    preset_terms(preset)  # an unknown preset is an error here too
    dropped = sorted(t for t in materials if t in SEED_MATERIALS)
    return {k: v for k, v in materials.items() if k not in SEED_MATERIALS}, dropped

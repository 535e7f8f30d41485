"""The one unit system of eyefem: mm, N, MPa (N/mm^2), seconds.

Pressures entered or reported in mmHg are converted here and nowhere else.
"""

MMHG = 1.33322e-4
"""One millimetre of mercury in MPa."""

KPA = 1e-3
"""One kilopascal in MPa (stresses are reported in kPa)."""


def mmhg_to_mpa(p_mmhg):
    """Convert a pressure in mmHg to MPa."""
    return p_mmhg * MMHG


def mpa_to_mmhg(p_mpa):
    """Convert a pressure in MPa to mmHg."""
    return p_mpa / MMHG

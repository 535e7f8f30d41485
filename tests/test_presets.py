"""Material presets against a case file's own [materials] tables: a preset named on the
command line wins over tables that restate another preset; a case-file preset overridden
by a table is said."""

import logging

import numpy as np

from eyefem.catalog import schemas
from eyefem.cli.main import with_material_preset
from eyefem.eye.presets import PHYSIOLOGICAL_SCLERA, SEED_MATERIALS, tissues_replaced
from eyefem.eye.surgery import _materials
from eyefem.fem.materials import MooneyRivlin
from eyefem.io.casefile import load_case


def test_a_command_line_preset_replaces_the_case_tables_of_the_eye(caplog):
    """Case 1 restates the seed's constants as [materials] tables: without dropping them
    `--materials physiological` would leave the seed's neo-Hookean sclera in place."""
    case = load_case("cases/surgery/case1.toml", schemas())
    assert set(SEED_MATERIALS) <= set(case.materials)
    with caplog.at_level(logging.WARNING, logger="eyefem"):
        new = with_material_preset(case, "physiological")
    assert new.parameters["materials_preset"] == "physiological"
    assert not set(SEED_MATERIALS) & set(new.materials)
    assert "replaces the case file's [materials] tables of choroid, ciliary_body, cornea" in caplog.text
    assert case.materials["sclera"].coeffs[1, 0] == 0.0833  # the loaded case is unchanged
    sclera = _materials(new.materials, "physiological")["sclera"].coeffs
    assert sclera[1, 0] == PHYSIOLOGICAL_SCLERA["c10"] and sclera[3, 0] == PHYSIOLOGICAL_SCLERA["c30"]


def test_bodies_keep_their_tables_under_a_preset():
    band = MooneyRivlin.from_terms("band", {"c10": 2.0})
    sclera = MooneyRivlin.from_terms("sclera", {"c10": 0.1})
    kept, dropped = tissues_replaced({"band": band, "sclera": sclera}, "physiological")
    assert kept == {"band": band} and dropped == ["sclera"]


def test_a_table_over_a_calibrated_tissue_is_said(caplog):
    sclera = MooneyRivlin.from_terms("sclera", {"c10": 0.1})
    with caplog.at_level(logging.WARNING):
        mats = _materials({"sclera": sclera}, "physiological")
    assert "[materials] tables of sclera replace the 'physiological' preset" in caplog.text
    assert np.array_equal(mats["sclera"].coeffs, sclera.coeffs)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _materials({"sclera": sclera}, "seed")  # cases 1-6: the seed's own values, no word
    assert "replace" not in caplog.text


def test_a_post_surgery_iop_above_perfusion_is_said(caplog):
    """Case 1 on the coarse physiological eye ends at 632 mmHg (closed cavity, stiff
    wall): the run must say why such a number comes out, and the seed cases (31-45
    mmHg on the default mesh) must not."""
    from eyefem.eye.surgery import warn_high_iop

    with caplog.at_level(logging.WARNING):
        assert warn_high_iop(632.0)
    assert "632 mmHg" in caplog.text and "cavity is closed" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert not warn_high_iop(44.8) and not warn_high_iop(float("nan"))
    assert caplog.text == ""


def test_a_broken_axial_symmetry_of_an_encircled_eye_is_said(caplog):
    """Default case 4 ovalises the globe (0.29 D of corneal astigmatism induced); the
    axisymmetric encircling cases induce below 0.01 D and must not be warned about."""
    from eyefem.eye.surgery import warn_broken_symmetry

    with caplog.at_level(logging.WARNING):
        assert warn_broken_symmetry(0.289)
    assert "0.29 D" in caplog.text and "load steps" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert not warn_broken_symmetry(0.004) and not warn_broken_symmetry(float("nan"))
    assert caplog.text == ""

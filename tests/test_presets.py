"""Material presets against a case file's own [materials] tables: a preset named on the
command line wins over tables that restate another preset; a case-file preset overridden
by a table is said."""

import logging

import numpy as np
import pytest

from eyefem.catalog import schemas
from eyefem.api import with_material_preset
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


@pytest.mark.parametrize("warner, above, said, below", [
    # case 1 on the coarse physiological eye ends at 632 mmHg (closed cavity, stiff wall);
    # the seed cases end at 31-45 mmHg on the default mesh
    ("warn_high_iop", 632.0, ("632 mmHg", "cavity is closed"), 44.8),
    # default case 4 ovalises the globe (0.29 D of corneal astigmatism induced); the
    # axisymmetric encircling cases induce below 0.01 D
    ("warn_broken_symmetry", 0.289, ("0.29 D", "load steps"), 0.004),
])
def test_a_suspect_surgical_outcome_is_said(caplog, warner, above, said, below):
    _suspect_is_said(caplog, warner, above, said, below)


@pytest.mark.parametrize("low, said, normal", [
    # case 1 on the coarse physiological eye with 250 uL drained ends at -49 mmHg
    (-49.1, ("-49.1 mmHg", "hypotony", "liquid under tension", "drain less"), 15.0),
    (3.2, ("3.2 mmHg", "hypotony", "drain less"), 21.0),
])
def test_an_over_drained_eye_is_said(caplog, low, said, normal):
    """A post-surgery IOP below hypotony (below zero: not physical) is said, with the fix."""
    _suspect_is_said(caplog, "warn_low_iop", low, said, normal)
    if low > 0:
        assert "not physical" not in caplog.text


def _suspect_is_said(caplog, warner, flagged, said, quiet):
    """A run says why a suspect number comes out (a post-surgery IOP above perfusion or
    below hypotony, an encircled eye that left its axial symmetry), and stays quiet for
    the seed cases."""
    from eyefem.eye import surgery

    warn = getattr(surgery, warner)
    with caplog.at_level(logging.WARNING):
        assert not warn(quiet) and not warn(float("nan"))
    assert caplog.text == ""
    with caplog.at_level(logging.WARNING):
        assert warn(flagged)
    assert all(words in caplog.text for words in said), caplog.text


def test_a_mesh_too_big_for_the_machine_is_said(caplog, monkeypatch):
    """A level whose run would not fit in this machine's memory is said before the run,
    with the fix; the case files' level on a 23 GB machine is not."""
    from eyefem.eye import surgery

    monkeypatch.setattr(surgery, "physical_memory_kb", lambda: 23.0 * 1024 ** 2)
    with caplog.at_level(logging.WARNING):
        assert not surgery.warn_memory(25166, "fine")  # about 5.5 GB
    assert caplog.text == ""
    monkeypatch.setattr(surgery, "physical_memory_kb", lambda: 8.0 * 1024 ** 2)
    with caplog.at_level(logging.WARNING):
        assert surgery.warn_memory(72920, "finest")  # about 14 GB on 8 GB
    assert all(w in caplog.text for w in ("'finest' (72920 hexahedra)", "about 14 GB",
                                           "has 8 GB", "--mesh fine"))

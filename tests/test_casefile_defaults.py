"""A surgery case file that gives only the buckle and its tightening runs the model whose
outcomes converge with the mesh (eyefem.eye.surgery.CONVERGING_MODEL): the schema's
defaults are that model, and ``model = "earlier"`` is the one switch to the earlier one."""

import json

import numpy as np
import pytest

from eyefem.catalog import schemas
from eyefem.eye.surgery import (CONVERGING_MODEL, EARLIER_MODEL, SURGERY_FIELDS,
                                check_parameters, model_fields, resolve_model, solver_settings,
                                surgery)
from eyefem.io.casefile import CaseError, load_case, with_mesh, with_parameters

SHORT = '[case]\nproblem = "surgery"\n[parameters]\nbuckle = "{buckle}"\ntightening = {t}\n'


def _case(tmp_path, buckle, tightening=5.0, extra="", name="short.toml"):
    path = tmp_path / name
    path.write_text(SHORT.format(buckle=buckle, t=tightening) + extra)
    return load_case(path, schemas())


def _written_out(buckle):
    """The applicable model fields as ``new-case`` writes them: TOML lines."""
    values = {**{f.name: f.default for f in SURGERY_FIELDS}, "buckle": buckle}
    return "".join(f"{k} = {v!r}\n" for k, v in model_fields(values).items())


@pytest.mark.parametrize("buckle, tightening, applies", [
    ("tire_flat", 5.0, {"lens_support", "buckle_edge"}),
    ("band", 5.0, {"lens_support", "buckle_edge"}),
    ("tire_ridged", 10.0, {"lens_support", "buckle_edge", "ridge_flank"}),
    ("sponge_radial", 0.0, {"lens_support", "sponge_end"})])
def test_a_short_case_resolves_to_the_converged_model(tmp_path, buckle, tightening, applies):
    short = _case(tmp_path, buckle, tightening)
    p = resolve_model(short.parameters)
    check_parameters(p)
    fields = model_fields(p)
    assert set(fields) == applies
    assert fields == {k: CONVERGING_MODEL[k] for k in applies}
    # the same case with those fields written out (as new-case writes them) is the same case
    full = _case(tmp_path, buckle, tightening, _written_out(buckle), name="full.toml")
    assert resolve_model(full.parameters) == p
    # a rigid sponge with rounded ends and a ridged tire want the curved contact's solver
    assert solver_settings(p) == ({"contact_curvature": 1e-3}
                                  if buckle in ("tire_ridged", "sponge_radial") else {})


def test_the_earlier_model_is_one_switch(tmp_path):
    early = resolve_model(_case(tmp_path, "tire_ridged", 10.0,
                                'model = "earlier"\n').parameters)
    assert {k: early[k] for k in EARLIER_MODEL} == EARLIER_MODEL
    assert (early["buckle_edge"], early["ridge_flank"], early["lens_support"]) == (0.5, 1.0, 0.0)
    # the switch sets its fields: a case giving one of them another value is refused
    clash = _case(tmp_path, "tire_flat", 5.0, 'model = "earlier"\nbuckle_edge = 0.7\n',
                  name="clash.toml")
    with pytest.raises(ValueError, match=r"buckle_edge = 0.7 with model = 'earlier'.*remove "
                                         r"buckle_edge or set model = 'converged'"):
        check_parameters(clash.parameters)
    with pytest.raises(CaseError, match=r"'model' = 'old'.*one of \['converged', 'earlier'\]"):
        _case(tmp_path, "tire_flat", 5.0, 'model = "old"\n', name="bad.toml")
    # lens_support means one thing: N/mm in all (the per-node springs are the switch's)
    with pytest.raises(CaseError, match=r"'lens_support' = 0.0 is out of range: 1e-4 to 100"):
        _case(tmp_path, "tire_flat", 5.0, "lens_support = 0.0\n", name="zero.toml")


@pytest.fixture(scope="module")
def coarse_setups(tmp_path_factory):
    """The short flat-tire case and the same with its model fields written out, built on
    the coarse eye (no solve), with the earlier model's for contrast."""
    tmp = tmp_path_factory.mktemp("cases")
    out = {}
    for name, extra in (("short", ""), ("full", _written_out("tire_flat")),
                        ("earlier", 'model = "earlier"\n')):
        case = _case(tmp, "tire_flat", 5.0, extra, name=f"{name}.toml")
        out[name] = surgery({**case.parameters, "mesh": "coarse"}, case.materials)
    return out


def _flat(theta) -> dict:
    return {f"{t}.{k}": np.asarray(v) for t, ps in theta.items() for k, v in ps.items()}


def test_the_short_case_builds_the_written_out_model(coarse_setups):
    short, full, early = (coarse_setups[k] for k in ("short", "full", "earlier"))
    assert short.parts.p == full.parts.p
    a, b = _flat(short.model.theta0()), _flat(full.model.theta0())
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    for s in (short, full):
        ring = s.model.term("buckle")
        assert ring.edge_width == CONVERGING_MODEL["buckle_edge"]
        springs = s.model.term("lens_springs")
        assert springs.params["k"] * len(springs.nodes) == pytest.approx(0.343, rel=1e-14)
    # the earlier model: 0.5 mm edges, 1e-3 N/mm on each of the coarse lens's 125 nodes
    assert early.model.term("buckle").edge_width == 0.5
    springs = early.model.term("lens_springs")
    assert float(np.asarray(springs.params["k"])) == 1e-3 and len(springs.nodes) == 125


@pytest.mark.slow
def test_the_short_case_runs_the_written_out_case(tmp_path):
    """Both cases run on the coarse eye (about 2 x 1 minute): the same outcomes."""
    from eyefem.cli.main import main

    summaries = []
    for name, extra in (("short", ""), ("full", _written_out("tire_flat"))):
        path = tmp_path / f"{name}.toml"
        path.write_text(SHORT.format(buckle="tire_flat", t=5.0) + extra)
        out = tmp_path / f"run_{name}"
        assert main(["-q", "run", str(path), "--mesh", "coarse", "--out", str(out),
                     "--no-vtu"]) == 0
        summaries.append(json.loads((out / "summary.json").read_text()))
    for k in ("iop_mmhg", "indentation_mm", "axial_length_change_mm", "max_suture_force_N"):
        assert summaries[0][k] == pytest.approx(summaries[1][k], rel=1e-12), k


@pytest.mark.parametrize("buckle, body, curvature", [
    ("tire_ridged", "rigid", 1e-3), ("sponge_radial", "rigid", 1e-3),
    ("tire_flat", "rigid", 0.0), ("tire_ridged", "deformable", 0.0)])
def test_a_short_case_gets_the_contact_tangent_its_buckle_wants(tmp_path, buckle, body,
                                                                curvature):
    """The problem's [solver] settings apply to a case that leaves them out (a rigid ridged
    tire's shoulders and a rounded sponge's ends: the contact tangent without their
    curvature early in each step); the case file's own setting wins."""
    from eyefem.catalog import solver_defaults

    text = SHORT.format(buckle=buckle, t=5.0) + f'buckle_body = "{body}"\n'
    path = tmp_path / "short.toml"
    path.write_text(text)
    assert load_case(path, schemas(), solver_defaults()).solver.contact_curvature == curvature
    assert load_case(path, schemas()).solver.contact_curvature == 0.0  # no defaults given
    path.write_text(text + "[solver]\ncontact_curvature = 0.0\n")
    assert load_case(path, schemas(), solver_defaults()).solver.contact_curvature == 0.0


def test_with_mesh_returns_a_new_case_and_leaves_the_loaded_one(tmp_path):
    """The case-file overrides of the CLI and the benchmarks (``--mesh``) build new Case
    objects: the loaded case keeps its parameters."""
    case = _case(tmp_path, "band")
    coarse = with_mesh(case, "coarse")
    assert coarse.parameters["mesh"] == "coarse" and coarse.parameters["buckle"] == "band"
    assert case.parameters["mesh"] == SURGERY_DEFAULTS["mesh"] != "coarse"
    both = with_parameters(case, mesh="coarse", symmetry="none")
    assert (both.parameters["mesh"], both.parameters["symmetry"]) == ("coarse", "none")
    assert case.parameters["symmetry"] == SURGERY_DEFAULTS["symmetry"]
    with pytest.raises(CaseError, match="has no parameter 'tightning'.*did you mean 'tightening'"):
        with_parameters(case, tightning=4.0)


SURGERY_DEFAULTS = {f.name: f.default for f in SURGERY_FIELDS}

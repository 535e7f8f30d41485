"""The case-file dialogue: scripted answers, re-asking on invalid input, flags only."""

import pytest

from eyefem.catalog import problems
from eyefem.cli.dialogue import new_case, scripted
from eyefem.cli.main import main as cli_main
from eyefem.eye.surgery import run_mesh_error
from eyefem.io.casefile import CaseError, load_case

PROBLEMS = problems()

SCHEMAS = {k: v[0] for k, v in PROBLEMS.items()}


def test_scripted_dialogue_reasks_and_writes_a_valid_case(tmp_path):
    fields = PROBLEMS["uniaxial"][0]  # stretch, n, steps
    said = []
    answers = ["-2", "big", "2.5", "", "4"]  # two invalid stretches, then 2.5; n default; steps 4
    path = new_case("uniaxial", fields, tmp_path / "u.toml", ask=scripted(answers),
                    say=said.append)
    assert sum("invalid" in s for s in said) == 2
    case = load_case(path, SCHEMAS)
    assert case.parameters["stretch"] == 2.5 and case.parameters["steps"] == 4
    assert case.parameters["n"] == 2


def test_flags_only_case_runs(tmp_path):
    out = tmp_path / "c.toml"
    assert cli_main(["-q", "new-case", "uniaxial", "-o", str(out), "--set", "stretch=1.5",
                     "--set", "steps=2", "--yes"]) == 0
    assert cli_main(["-q", "run", str(out), "--out", str(tmp_path / "res"), "--no-vtu"]) == 0
    assert (tmp_path / "res" / "summary.json").exists()


def test_bad_flags_are_reported(tmp_path, capsys):
    assert cli_main(["-q", "new-case", "uniaxial", "-o", str(tmp_path / "x.toml"),
                     "--set", "strech=2", "--yes"]) == 2
    assert "strech" in capsys.readouterr().err
    with pytest.raises(CaseError, match="no valid answer for 'stretch'"):
        new_case("uniaxial", PROBLEMS["uniaxial"][0], tmp_path / "y.toml",
                 ask=scripted(["-1"] * 5), say=lambda s: None)
    assert not (tmp_path / "y.toml").exists()


def test_answers_that_clash_across_fields_write_nothing(tmp_path, capsys):
    """Each answer can be valid alone and the combination not: a deformable body for a
    circumferential sponge, a band tension on a segmental sponge or with a prescribed
    tightening. The dialogue says which and writes no file."""
    for sets, words in ((["buckle=sponge_circumferential", "buckle_body=deformable"],
                         "'sponge_radial'; got 'sponge_circumferential'"),
                        (["buckle=sponge_radial", "band_tension=0.5"], "needs an encircling"),
                        (["band_tension=0.5", "tightening=5"], "give one")):
        out = tmp_path / "c.toml"
        args = ["-q", "new-case", "surgery", "-o", str(out), "--yes"]
        for s in sets:
            args += ["--set", s]
        assert cli_main(args) == 2
        err = capsys.readouterr().err
        assert words in err and "nothing written" in err
        assert not out.exists()


def _surgery_prompts(tmp_path, first_answers, ask_all=False):
    """(prompts asked, case written) of a surgery dialogue answered by ``first_answers``
    and Enter to the rest."""
    fields, build = PROBLEMS["surgery"]
    prompts, answers = [], iter(first_answers)

    def ask(prompt):
        prompts.append(prompt.split(":")[0])
        return next(answers, "")

    path = new_case("surgery", fields, tmp_path / "s.toml", ask=ask, say=lambda m: None,
                    check=build.check, questions=build.questions, ask_all=ask_all,
                    solver_settings=build.solver_settings)
    return prompts, load_case(path, SCHEMAS)


def test_a_sponge_is_asked_only_what_applies_with_its_own_defaults(tmp_path):
    prompts, case = _surgery_prompts(tmp_path, ["coarse", "sponge_radial"])
    assert prompts[:2] == ["mesh", "buckle"]
    assert "band_tension" not in prompts and "globe_torsion" not in prompts
    assert "buckle_meridian_deg" in prompts and "axial_length" in prompts
    p = case.parameters
    assert (p["n_sutures"], p["suture_width"], p["tightening"]) == (2, 8.5, 0.0)  # cases 5, 6


def test_an_encircling_buckle_is_not_asked_a_meridian(tmp_path):
    prompts, case = _surgery_prompts(tmp_path, ["coarse", "tire_flat"])
    assert "buckle_meridian_deg" not in prompts and "deformable_tightening" not in prompts
    assert "band_tension" in prompts and "tightening" in prompts
    assert case.parameters["n_sutures"] == 8 and len(prompts) < 20
    # a new case gets the calibrated tissues; a case file without the field, the seed's
    assert case.parameters["materials_preset"] == "physiological"
    assert "materials_preset" in prompts
    seed_field = next(f for f in PROBLEMS["surgery"][0] if f.name == "materials_preset")
    assert seed_field.default == "seed"


def _answered_by_name(tmp_path, answers: dict):
    """(prompts asked, case written) of a surgery dialogue that answers a field's prompt
    from ``answers`` (field name -> text) and Enter to the rest."""
    fields, build = PROBLEMS["surgery"]
    prompts = []

    def ask(prompt):
        name = prompt.split(":")[0]
        prompts.append(name)
        return answers.get(name, "")

    path = new_case("surgery", fields, tmp_path / "s.toml", ask=ask, say=lambda m: None,
                    check=build.check, questions=build.questions,
                    solver_settings=build.solver_settings)
    return prompts, load_case(path, SCHEMAS)


def test_a_new_case_on_the_calibrated_tissues_runs_on_the_timeline(tmp_path):
    """The calibrated eye's closed cavity loses no liquid (a new case's surgery ended at
    622 mmHg on the coarse mesh): a new case with those tissues and no drained volume is
    asked for the timeline and gets it by default (volume_regulation = true, written in the
    case), its stages run on to the follow-up; with the seed's tissues, or a drained
    volume, the question is not asked and the cavity stays closed."""
    from eyefem.eye.surgery import surgery

    prompts, case = _answered_by_name(tmp_path, {"mesh": "coarse", "buckle": "tire_flat"})
    assert "volume_regulation" in prompts
    assert case.parameters["materials_preset"] == "physiological"
    assert case.parameters["volume_regulation"] is True
    stages = surgery(case.parameters, case.materials).stages
    assert [st.name for st in stages][-1] == "follow-up"
    for i, answers in enumerate(({"materials_preset": "seed"}, {"drain_volume": "170"})):
        folder = tmp_path / str(i)
        folder.mkdir()
        prompts, case = _answered_by_name(folder, {"mesh": "coarse", **answers})
        assert "volume_regulation" not in prompts, answers
        assert case.parameters["volume_regulation"] is False, answers
        assert "volume_regulation" not in (folder / "s.toml").read_text(), answers
    # an answer of no keeps the closed cavity, and says so in the case
    folder = tmp_path / "no"
    folder.mkdir()
    prompts, case = _answered_by_name(folder, {"volume_regulation": "no"})
    assert case.parameters["volume_regulation"] is False
    assert "volume_regulation = false" in (folder / "s.toml").read_text()


def test_a_new_case_gets_the_case_files_converging_model(tmp_path):
    # docs/convergence.md: the case files' model (1 mm tire edges, the ridge's 1.5 mm
    # flanks, 0.343 N/mm of lens springs in all, a rigid sponge's ends rounded over 1 mm)
    # converges with the mesh; the fields' own
    # defaults are that model too, and a new case states it
    fields = {f.name: f.default for f in PROBLEMS["surgery"][0]}
    out = {"iop_mmhg": 40.0, "indentation_mm": 1.0}
    # and, like the case files 2-6, a rigid buckle whose surface curves sharply under the
    # nodes it presses (ridge shoulders, rounded sponge ends) gets contact_curvature = 1e-3
    for answers, edge, flank, end, curv in (
            (["coarse", "tire_ridged"], 1.0, 1.5, 1.0, 1e-3),
            (["coarse", "tire_flat"], 1.0, 1.5, 1.0, 0.0),
            (["coarse", "band"], 1.0, 1.5, 1.0, 0.0),
            (["coarse", "sponge_radial"], 1.0, 1.5, 1.0, 1e-3),
            (["coarse", "sponge_radial", "deformable"], 1.0, 1.5, 1.0, 0.0),
            (["coarse", "tire_flat", "deformable"], 1.0, 1.5, 1.0, 0.0)):
        folder = tmp_path / "_".join(answers)
        folder.mkdir()
        _, case = _surgery_prompts(folder, answers)
        p = case.parameters
        assert p["lens_support"] == 0.343, answers
        assert (p["buckle_edge"], p["ridge_flank"], p["sponge_end"]) == (edge, flank, end), \
            answers
        assert case.solver.contact_curvature == curv, answers
        assert ("[solver]" in (folder / "s.toml").read_text()) == bool(curv), answers
        err = run_mesh_error({**fields, **p, "mesh": "fine"},
                             not answers[1].startswith("sponge"), out)
        assert "another model" not in err["note"], (answers, err["note"])
    assert (fields["buckle_edge"], fields["ridge_flank"], fields["lens_support"],
            fields["sponge_end"]) == (1.0, 1.5, 0.343, 1.0)


def test_new_case_all_asks_every_field(tmp_path):
    prompts, _ = _surgery_prompts(tmp_path, ["coarse", "tire_flat"], ask_all=True)
    assert prompts == [f.name for f in PROBLEMS["surgery"][0]]


@pytest.mark.parametrize("buckle, body, curvature", [("sponge_radial", "rigid", 1e-3),
                                                      ("tire_ridged", "deformable", 0.0)])
def test_new_case_from_the_command_line_writes_the_solver_section(tmp_path, buckle, body,
                                                                   curvature):
    out = tmp_path / "c.toml"
    assert cli_main(["-q", "new-case", "surgery", "-o", str(out), "--yes", "--set",
                     f"buckle={buckle}", "--set", f"buckle_body={body}"]) == 0
    assert load_case(out, SCHEMAS).solver.contact_curvature == curvature


def test_a_mistyped_choice_gets_a_did_you_mean(tmp_path, capsys):
    out = tmp_path / "c.toml"
    assert cli_main(["-q", "new-case", "surgery", "-o", str(out), "--yes",
                     "--set", "buckle=tire_flt"]) == 2
    err = capsys.readouterr().err
    assert "'tire_flt' is out of range" in err and "(did you mean 'tire_flat'?)" in err
    assert not out.exists()

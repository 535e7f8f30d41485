"""``eyefem describe``: a problem's fields, what a user changes first at the top, the
numerical settings and model details under the advanced heading."""

from eyefem.cli.main import main
from eyefem.eye.surgery import ADVANCED_FIELDS, DESCRIBE_FIRST, SURGERY_FIELDS
from eyefem.io.casefile import ADVANCED_HEADING


def _listed(out: str) -> tuple[list[str], list[str]]:
    """(field names above the advanced heading, field names below it), in printed order."""
    lines = out.splitlines()
    start = lines.index("[parameters]") + 1
    cut = lines.index(ADVANCED_HEADING) if ADVANCED_HEADING in lines else len(lines)
    names = [[ln.split()[0] for ln in part if ln.startswith("  ")]
             for part in (lines[start:cut], lines[cut + 1:])]
    return names[0], names[1]


def test_describe_surgery_puts_first_what_a_user_changes_first(capsys):
    assert main(["describe", "surgery"]) == 0
    first, advanced = _listed(capsys.readouterr().out)
    # every field once
    assert sorted(first + advanced) == sorted(f.name for f in SURGERY_FIELDS)
    # the buckle, its tightening, the sutures' placement, the tissues, drainage and the
    # timeline's switch lead, in that order
    assert first[:len(DESCRIBE_FIRST)] == list(DESCRIBE_FIRST)
    assert first[:3] == ["buckle", "buckle_body", "tightening"]
    assert first.index("suture_width") < first.index("materials_preset") \
        < first.index("drain_volume") < first.index("volume_regulation")
    # the numerical and model details under the heading, in schema order
    assert set(advanced) == ADVANCED_FIELDS - set(DESCRIBE_FIRST)
    order = [f.name for f in SURGERY_FIELDS]
    assert advanced == sorted(advanced, key=order.index)
    for name in ("steps_tighten", "contact_smoothing", "buckle_edge", "ridge_flank",
                 "sponge_end", "lens_support", "model", "n_segments", "wall_element"):
        assert name in advanced, name
    assert "mesh" in first and "axial_length" in first


def test_describe_shows_the_converged_defaults(capsys):
    assert main(["describe", "surgery"]) == 0
    rows = {ln.split()[0]: ln.split()[3] for ln in capsys.readouterr().out.splitlines()
            if ln.startswith("  ")}
    assert (rows["buckle_edge"], rows["ridge_flank"], rows["sponge_end"],
            rows["lens_support"], rows["model"]) == ("1", "1.5", "1", "0.343", "'converged'")
    assert rows["anterior_chamber_depth"] == "3.6"  # floats printed to 12 digits


def test_describe_without_groups_lists_the_schema_as_it_is(capsys):
    from eyefem.catalog import schemas

    assert main(["describe", "equibiaxial_sheet"]) == 0
    out = capsys.readouterr().out
    assert ADVANCED_HEADING not in out
    first, advanced = _listed(out)
    assert first == [f.name for f in schemas()["equibiaxial_sheet"]] and advanced == []

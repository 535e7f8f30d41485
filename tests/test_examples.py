"""The seed's liquid-container examples: closed-cylinder and band meshes, pipes squeezed
between rigid plates (one cavity each), a liquid-filled cylinder tightened by a band."""

from pathlib import Path

import numpy as np
import pytest

from eyefem.catalog import problems
from eyefem.fem import vessels
from eyefem.fem.cavity import FluidCavity
from eyefem.fem.mesh import open_edges
from eyefem.io.casefile import load_case

PROBLEMS = problems()
from eyefem.run.runner import run_setup
from eyefem.problems.examples import CONTAINER_FIELDS, banded_container, compressed_pipes

ROOT = Path(__file__).resolve().parents[1]


def test_closed_cylinder_cavity_is_closed_and_holds_the_prism_volume():
    ri, h, L, n = 2.5, 0.5, 10.0, 16
    m = vessels.closed_cylinder(ri, h, L, n, 1, 8)
    assert len(open_edges(m.face_set("cavity"))) == 0
    assert len(open_edges(m.face_set("outer"))) == 0
    assert m.jacobian_ratio().min() > 0.3
    v = FluidCavity("c", m, "cavity", bulk=1.0).params["v_ini"]
    assert float(v) == pytest.approx(0.5 * n * ri**2 * np.sin(2 * np.pi / n) * L, rel=1e-12)
    X = m.nodes
    r = np.hypot(X[:, 0], X[:, 1])
    assert np.allclose(r[m.node_set("rim_y0")], ri + h) and len(m.node_set("rim_y0")) == 2
    with pytest.raises(ValueError, match="multiple of 8"):
        vessels.closed_cylinder(ri, h, L, 12, 1, 8)
    with pytest.raises(ValueError, match="n_len = 7"):
        vessels.closed_cylinder(ri, h, L, 16, 1, 7)


def test_slit_band_has_two_coincident_free_ends():
    b = vessels.slit_band(3.0, 0.6, 2.5, 32, 1, 2, z_centre=5.0)
    e0, e1 = b.node_set("end0"), b.node_set("end1")
    assert len(np.intersect1d(e0, e1)) == 0
    assert np.allclose(b.nodes[e0], b.nodes[e1])  # cut, not merged
    f = b.face_set("inner")
    x = b.nodes[f]
    nrm = np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1])
    assert np.all(np.einsum("fi,fi->f", nrm[:, :2], x[:, :, :2].mean(1)) < 0)  # toward the axis
    assert np.allclose(np.hypot(*x[..., :2].transpose(2, 0, 1)), 3.0)


@pytest.fixture(scope="module")
def pipes(tmp_path_factory):
    case = load_case(ROOT / "cases/examples/pipes.toml", {k: v[0] for k, v in PROBLEMS.items()})
    return run_setup(compressed_pipes(case.parameters, case.materials),
                     tmp_path_factory.mktemp("pipes"))


def test_each_squeezed_pipe_has_its_own_pressure(pipes):
    s, rows = pipes.summary, pipes.rows
    P = [s[f"pipe{k}_pressure_kPa"] for k in range(3)]
    assert 0 < P[0] < P[1] < P[2]  # more squeeze, more pressure, cavity by cavity
    for k in range(3):  # and it grows step by step
        assert np.all(np.diff([r[f"pipe{k}_pressure_kPa"] for r in rows]) > 0)
    # the supports lie on mirror planes of geometry and load: they carry nothing
    assert s["max_support_reaction_N"] < 1e-9
    last = rows[-1]
    assert last["plates/active"] > 0
    assert last["plates/max_penetration_mm"] < 0.05 * s["pipe0_squeeze_mm"]
    # nearly incompressible liquid: volume change = -P V / K
    for k in range(3):
        v0, v = rows[0][f"liquid/pipe{k}/cavity/volume_mm3"], last[f"liquid/pipe{k}/cavity/volume_mm3"]
        assert abs(v / v0 - 1) < 1e-5


def test_pipe_outputs_open_in_paraview(pipes):
    import meshio

    out = pipes.out_dir
    for f in ("pipes.pvd", "pipes_history.csv", "pipes_pressure.png"):
        assert (out / f).exists(), f
    m = meshio.read(sorted((out / "vtu").glob("*.vtu"))[-1])
    assert "von_mises" in m.cell_data and "liquid_pressure_MPa" in m.point_data
    assert np.max(m.point_data["liquid_pressure_MPa"]) > 0


@pytest.fixture(scope="module")
def container(tmp_path_factory):
    p = {f.name: f.default for f in CONTAINER_FIELDS}
    p.update(n_circ=24, n_len=6, steps=8)  # coarser than the case file, for speed
    return run_setup(banded_container(p, None), tmp_path_factory.mktemp("container"),
                     vtu=False, plots=False)


def test_band_squeezes_the_container_and_raises_its_pressure(container):
    s, rows = container.summary, container.rows
    assert s["shortening_mm"] == pytest.approx(2.0)
    for key in ("pressure_kPa", "band_tension_N"):
        v = np.array([r[key] for r in rows])
        assert v[0] > 0 and np.all(np.diff(v) > 0), key
    assert s["radius_at_band_mm"] < s["initial_outer_radius_mm"] - 0.1
    # a frictionless band of tension T wrapped once around a cylinder presses on it with
    # a total normal force 2 pi T (line load T / R over the circumference); the straight
    # ends beyond the slit and the coarse band make it approximate
    last = rows[-1]
    assert last["contact/force_N"] == pytest.approx(2 * np.pi * s["band_tension_N"], rel=0.1)
    assert last["contact/active"] > 0
    assert abs(last["liquid/volume_mm3"] / rows[0]["liquid/volume_mm3"] - 1) < 1e-5
    # the supports stand on mirror planes; what they carry is the faceted contact's torque
    assert s["max_support_reaction_N"] < 0.03 * s["band_tension_N"]


def test_bad_example_parameters_name_the_file_and_leave_no_output(tmp_path, capsys):
    from eyefem.cli.main import main as cli_main

    text = (ROOT / "cases/examples/pipes.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("steps = 6", "steps = 6\nn_circ = 12"))
    out = tmp_path / "out"
    assert cli_main(["-q", "run", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "n_circ = 12" in err and "multiple of 8" in err
    bad.write_text(text.replace("[materials.wall]", "[materials.walls]"))
    assert cli_main(["-q", "run", str(bad), "--out", str(out)]) == 2
    assert "unknown material 'walls'" in capsys.readouterr().err
    assert not out.exists()

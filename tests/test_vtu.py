"""VTU / PVD output: the time series (monotone times, undeformed frame first, stage and
material names as field data, further datasets as parts), NaN fields of terms inactive in
a stage, reaction forces and Green-Lagrange strain; a coarse case 1 run read frame by
frame (slow)."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.bars import Bars
from eyefem.fem.materials import mooney_rivlin
from eyefem.fem.rigid import plane
from eyefem.fem.rigid_contact import RigidContact
from eyefem.fem.surface import PressureLoad
from eyefem.solve.problem import Setup
from eyefem.run.runner import cell_and_point_fields, run_setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage

PULL = 0.2  # mm: the unit cube is stretched to 1.2 in the first stage
PRESS = 0.5  # MPa on the x1 face in the second stage


def _pvd(path):
    """[(time, part, name, file)] of a .pvd file."""
    root = ET.parse(path).getroot()
    return [(float(d.get("timestep")), int(d.get("part")), d.get("name"), d.get("file"))
            for d in root.iter("DataSet")]


def _cube_setup():
    """One Mooney-Rivlin element with a bar along its x edge: stage 'pull' prescribes
    x = 0.2 mm on the face x1 (the pressure load inactive), stage 'press' frees it and
    applies 0.5 MPa (load active). Two steps each."""
    mesh = generators.box(1.0, 1.0, 1.0, 1, 1, 1, material="rubber")
    mat = mooney_rivlin("rubber", 25.0, 5.0)
    a = int(np.intersect1d(mesh.node_set("x0"), np.intersect1d(mesh.node_set("y0"),
                                                                 mesh.node_set("z0")))[0])
    b = int(np.intersect1d(mesh.node_set("x1"), np.intersect1d(mesh.node_set("y0"),
                                                                 mesh.node_set("z0")))[0])
    tie = Bars("tie", np.full((1, 4), a), np.full((1, 4), b), np.zeros((1, 2)),
               np.zeros((1, 2)), mesh.nodes, EA=1.0)
    model = solid_model(mesh, {"rubber": mat}, (PressureLoad("load", mesh, "x1"), tie))
    fix = [(s, c) for s, c in (("x0", "x"), ("y0", "y"), ("z0", "z"))]
    held = np.concatenate([node_dofs(mesh.node_set(s), c) for s, c in fix])
    held = np.unique(held)
    x1 = node_dofs(mesh.node_set("x1"), "x")
    stages = [Stage("pull", 2, (np.r_[held, x1], np.r_[np.zeros(len(held)),
                                                         np.full(len(x1), PULL)]),
                    active=("solid", "tie")),
              Stage("press", 2, (held, np.zeros(len(held))), params={"load": {"p": PRESS}},
                    active=("solid", "tie", "load"))]
    return Setup("cube", model, stages, lambda m, q, th: {}, lambda rows, out, plots: {})


@pytest.fixture(scope="module")
def cube_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("cube")
    run_setup(_cube_setup(), out, plots=False)
    return out


def test_series_times_parts_and_field_data(cube_run):
    out = cube_run
    entries = _pvd(out / "cube.pvd")
    main = [e for e in entries if e[2] == "cube"]
    tie = [e for e in entries if e[2] == "tie"]
    # undeformed frame first, then stage index + load factor
    assert [e[0] for e in main] == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0], abs=1e-12)
    assert [e[0] for e in tie] == [e[0] for e in main]
    assert {e[1] for e in main} == {0} and {e[1] for e in tie} == {1}
    times = [e[0] for e in entries]
    assert times == sorted(times)
    assert all((out / e[3]).exists() for e in entries)
    m0 = meshio.read(out / main[0][3])
    assert np.all(m0.point_data["displacement"] == 0.0)
    fd = m0.field_data
    assert fd["stage:pull"][0] == 0 and fd["stage:press"][0] == 1
    assert fd["material:rubber"][0] == 0
    for k, e in enumerate(main):
        fd = meshio.read(out / e[3]).field_data
        assert fd["time"][0] == pytest.approx(e[0])
        assert fd["stage"][0] == (0 if e[0] <= 1.0 else 1)
    # the bar as a line with its force, NaN-free (the bar is active in both stages)
    last = meshio.read(out / tie[-1][3])
    assert last.cells[0].type == "line" and len(last.cells[0].data) == 1
    assert np.isfinite(last.cell_data["force_N"][0]).all()
    assert last.cell_data["active"][0][0] == 1


def test_inactive_terms_are_nan(cube_run):
    out = cube_run
    main = [e for e in _pvd(out / "cube.pvd") if e[2] == "cube"]
    frames = [meshio.read(out / e[3]) for e in main]
    x1 = generators.box(1.0, 1.0, 1.0, 1, 1, 1).node_set("x1")
    for e, m in zip(main, frames):
        p = m.point_data["load_pressure_MPa"]
        if e[0] <= 1.0:  # 'load' inactive in the undeformed frame and in stage 'pull'
            assert np.all(np.isnan(p))
        else:  # ramped to PRESS over stage 'press'
            assert p[x1] == pytest.approx(PRESS * (e[0] - 1.0))
        assert set(m.cell_data) >= {"material", "cauchy", "green_lagrange",
                                    "max_principal_strain"}


def test_reactions_and_strain(cube_run):
    out = cube_run
    main = [e for e in _pvd(out / "cube.pvd") if e[2] == "cube"]
    m = meshio.read(out / main[2][3])  # end of 'pull': homogeneous stretch 1.2
    E = m.cell_data["green_lagrange"][0].reshape(3, 3)
    assert E[0, 0] == pytest.approx((1.2**2 - 1) / 2, rel=1e-9)
    assert m.cell_data["max_principal_strain"][0][0] == pytest.approx(0.22, rel=1e-9)
    R = m.point_data["reaction_force_N"]
    x = m.points
    pull = R[np.isclose(x[:, 0], 1.0), 0].sum()
    assert pull > 1.0  # the supports pull the face x1 out
    assert R[:, 0].sum() == pytest.approx(0.0, abs=1e-8 * pull)  # no other load: balanced
    m = meshio.read(out / main[-1][3])  # end of 'press': x1 free, 0.5 MPa on it
    R = m.point_data["reaction_force_N"]
    assert np.all(R[np.isclose(m.points[:, 0], 1.0), 0] == 0.0)  # not prescribed there
    assert np.all(np.isfinite(R))


def test_unpaired_rigid_contact_gap_is_nan():
    """A plate over the face x1 only pairs the nodes of x1; the others get a NaN gap."""
    mesh = generators.box(1.0, 1.0, 1.0, 2, 2, 2)
    body = plane("plate", (1.05, 0.5, 0.5), (-1.0, 0.0, 0.0), 2.0, direction=(-1.0, 0, 0))
    c = RigidContact("c", mesh, "all", (body,), search_gap=0.1)
    model = solid_model(mesh, {"default": mooney_rivlin("default", 1.0, 0.0)}, (c,))
    q = np.zeros(model.n_dof)
    point, _ = cell_and_point_fields(model, q, model.theta0())
    gap = point["c_gap_mm"]
    on = np.isclose(mesh.nodes[:, 0], 1.0)
    assert gap[on] == pytest.approx(0.05)
    assert np.all(np.isnan(gap[~on]))
    pts, kind, tris, _ = c.geometry(q, model.theta0()["c"])
    assert kind == "triangle" and pts[:, 0] == pytest.approx(1.05) and len(tris) == 32
    point, _ = cell_and_point_fields(model, q, model.theta0(), active=("solid",))
    assert np.all(np.isnan(point["c_gap_mm"])) and np.all(np.isnan(point["c_pressure_MPa"]))


@pytest.mark.slow
def test_coarse_case1_frames(tmp_path_factory):
    """Every frame of coarse case 1 (issue 32): cavity pressure in [0, 0.02] MPa where
    defined, no contact pressure in the pressurise stage, no gap above 100 mm, buckle and
    suture datasets present, monotone times, the undeformed frame first."""
    from eyefem.cli.main import main

    out = tmp_path_factory.mktemp("case1")
    assert main(["-q", "run", "cases/surgery/case1.toml", "--mesh", "coarse",
                 "--out", str(out)]) == 0
    entries = _pvd(out / "surgery.pvd")
    times = [e[0] for e in entries]
    assert times == sorted(times) and times[0] == 0.0
    names = {e[2] for e in entries}
    assert {"surgery", "buckle", "sutures"} <= names
    main_frames = [e for e in entries if e[2] == "surgery"]
    assert [e[0] for e in main_frames] == sorted({e[0] for e in entries})
    for name in ("buckle", "sutures"):  # every part in every frame
        assert [e[0] for e in entries if e[2] == name] == [e[0] for e in main_frames]
    first = meshio.read(out / main_frames[0][3])
    assert np.all(first.point_data["displacement"] == 0.0)
    pressurise = first.field_data["stage:pressurise"][0]
    defined = 0
    for t, _, _, f in main_frames:
        m = meshio.read(out / f)
        stage = m.field_data["stage"][0]
        for k, v in m.point_data.items():
            if re.fullmatch(r"(cavity|iop)_pressure_MPa", k):
                v = v[np.isfinite(v) & (v != 0.0)]  # 0 off the wetted surface
                defined += len(v) > 0
                assert np.all((v >= 0.0) & (v <= 0.02)), (f, k, v.min(), v.max())
            if k.endswith("_gap_mm"):
                assert np.nanmax(np.abs(v), initial=0.0) <= 100.0, (f, k)
            if k == "buckle_pressure_MPa" and stage == pressurise:
                assert np.all(np.isnan(v) | (v == 0.0)), (f, k)
    assert defined >= len(main_frames) - 1  # every deformed frame shows a fluid pressure
    last = {e[2]: e for e in entries if e[0] == times[-1]}
    sut = meshio.read(out / last["sutures"][3])
    assert sut.cells[0].type == "line"
    f = sut.cell_data["force_N"][0]
    assert np.all(np.isfinite(f)) and f.max() > 0.0
    buckle = meshio.read(out / last["buckle"][3])
    assert buckle.cells[0].type == "triangle" and len(buckle.cells[0].data) > 100


@pytest.mark.parametrize("shape", ["ring", "sponge", "curved"])
def test_buckle_gap_only_over_the_footprint_and_its_surface(shape):
    """The analytic buckle: a finite gap (below 100 mm) only at candidates over its
    footprint, NaN elsewhere (no 1.5e4 mm fade-out values); the exported surface lies at
    the buckle's radius (moved by d) and, for the ring, across its width."""
    from eyefem.fem.buckle_contact import BuckleContact

    R, d = 12.0, 0.3
    shell = generators.spherical_shell(11.0, 1.0, 8, 1)
    kw = ({"theta_b": np.pi / 2, "width": 4.0} if shape == "ring" else
          {"n0": (1.0, 0, 0), "m0": (0, 0, -1.0), "axis": (0, 0, -1.0), "sponge_radius": 2.0,
           "sponge_length": 8.0, "curved": shape == "curved"})
    t = BuckleContact("b", shell, "outer", "sponge" if shape != "ring" else "ring", R, **kw)
    params = {**t.params, "d": np.full(1, d)}
    q = np.zeros(3 * shell.n_nodes)
    gap = t.point_fields(q, params, shell.n_nodes)["b_gap_mm"]
    on = np.isfinite(gap)
    assert 0 < on.sum() < len(t.nodes) and np.abs(gap[on]).max() < 5.0
    pts, kind, tris, _ = t.geometry(q, params)
    assert kind == "triangle" and tris.max() < len(pts)
    if shape == "ring":
        assert np.linalg.norm(pts, axis=1) == pytest.approx(R - d, abs=0.31)  # + lifted edges
        assert np.abs(pts[:, 2]).max() == pytest.approx(2.0, abs=0.05)
    else:  # tube of radius 2 around an axis 14 - d from the centre
        c = np.linalg.norm(pts - (R + 2.0 - d) * np.array([1.0, 0, 0]), axis=1)
        assert c.min() >= 0.0 and pts[:, 0].min() == pytest.approx(R - d, abs=0.5)


def _xdmf_frames(path):
    """(points, hexahedra, [(time, point_data, cell_data name -> array)]) of an XDMF series
    read back with meshio's TimeSeriesReader."""
    from meshio.xdmf import TimeSeriesReader

    with TimeSeriesReader(path) as r:
        points, cells = r.read_points_cells()
        frames = []
        for k in range(r.num_steps):
            t, pd, cd = r.read_data(k)
            frames.append((t, pd, {n: v[0] for n, v in cd.items()}))
    return points, cells[0].data, frames


def _assert_xdmf_matches_vtu(out, name):
    """The XDMF series of ``out`` holds the main VTU frames: same times (monotone), same
    reference mesh, the same point and cell fields with the same values (NaN included)."""
    main = [e for e in _pvd(out / f"{name}.pvd") if e[2] == name]
    points, hexes, frames = _xdmf_frames(out / f"{name}.xdmf")
    times = [t for t, _, _ in frames]
    assert times == [e[0] for e in main] and times == sorted(times) and times[0] == 0.0
    for (t, pd, cd), e in zip(frames, main):
        m = meshio.read(out / e[3])
        np.testing.assert_array_equal(points, m.points)
        np.testing.assert_array_equal(hexes, m.cells[0].data)
        assert set(pd) == set(m.point_data) and set(cd) == set(m.cell_data), t
        for k, v in m.point_data.items():
            np.testing.assert_allclose(pd[k], v, rtol=1e-15, atol=0.0, equal_nan=True,
                                       err_msg=f"point field {k} at time {t}")
        for k, v in m.cell_data.items():
            np.testing.assert_allclose(cd[k], v[0], rtol=1e-15, atol=0.0, equal_nan=True,
                                       err_msg=f"cell field {k} at time {t}")


@pytest.fixture(scope="module", params=["XML", "HDF"])
def cube_xdmf_run(request, tmp_path_factory):
    """The cube run with both series; its XDMF arrays as XML text or in HDF5 (h5py)."""
    if request.param == "HDF":
        pytest.importorskip("h5py", reason="the HDF5 XDMF series needs h5py")
    out = tmp_path_factory.mktemp(f"cube-xdmf-{request.param}")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("eyefem.io.output.xdmf_data_format", lambda: request.param)
        run_setup(_cube_setup(), out, plots=False, xdmf=True)
    assert (out / "cube.h5").is_file() == (request.param == "HDF")
    return out


def test_xdmf_series_holds_the_vtu_frames(cube_xdmf_run):
    _assert_xdmf_matches_vtu(cube_xdmf_run, "cube")
    _, _, frames = _xdmf_frames(cube_xdmf_run / "cube.xdmf")
    assert np.all(np.isnan(frames[1][1]["load_pressure_MPa"]))  # inactive in 'pull'
    assert frames[-1][2]["cauchy"].shape == (1, 9)


def test_xdmf_series_survives_a_resume(cube_xdmf_run, tmp_path):
    """--resume keeps the XDMF frames of the completed stages (here: all of them)."""
    import shutil

    out = tmp_path / "resumed"
    shutil.copytree(cube_xdmf_run, out)
    with pytest.MonkeyPatch.context() as mp:
        fmt = "HDF" if (out / "cube.h5").is_file() else "XML"
        mp.setattr("eyefem.io.output.xdmf_data_format", lambda: fmt)
        run_setup(_cube_setup(), out, plots=False, xdmf=True, resume=True)
    _assert_xdmf_matches_vtu(out, "cube")
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".cube")) == []


@pytest.mark.parametrize("how", ["--xdmf", "[output] xdmf"])
def test_run_writes_xdmf_from_the_flag_or_the_case_file(tmp_path, how):
    """`eyefem run --xdmf` or the case file's `xdmf = true`: a small sheet's series, one
    frame per step after the undeformed one, without the VTU series."""
    from eyefem.cli.main import main

    case = tmp_path / "sheet.toml"
    case.write_text('[case]\nproblem = "equibiaxial_sheet"\n[parameters]\nside = 2.0\n'
                    "thickness = 0.5\nn_side = 2\nn_thick = 1\nstretch = 1.5\nsteps = 3\n"
                    "[materials.rubber]\nc10 = 0.1\n"
                    + ("[output]\nxdmf = true\n" if how.startswith("[") else ""))
    out = tmp_path / "out"
    args = ["-q", "run", str(case), "--out", str(out), "--no-vtu"]
    assert main(args + (["--xdmf"] if how == "--xdmf" else [])) == 0
    (path,) = out.glob("*.xdmf")
    assert not list(out.glob("*.pvd"))
    points, hexes, frames = _xdmf_frames(path)
    assert hexes.shape == (4, 8) and len(frames) == 4
    assert [t for t, _, _ in frames] == pytest.approx([0.0, 1 / 3, 2 / 3, 1.0])
    u = frames[-1][1]["displacement"]
    assert np.abs(u).max() == pytest.approx(0.5 * points[:, 0].max(), rel=1e-9)

"""A user's hexahedral mesh from a file (eyefem.io.meshfile, problem "user_mesh"): gmsh
physical groups as materials and sets, a homogeneous stretch against the closed form,
the case-file path relative to the case, and the errors for what cannot be used."""

import json

import meshio
import numpy as np
import pytest

from eyefem.catalog import schemas
from eyefem.cli.main import main as cli_main
from eyefem.fem.materials import mooney_rivlin
from eyefem.io.casefile import load_case
from eyefem.io.meshfile import MeshFileError, read_hex_mesh
from eyefem.problems.user_mesh import user_mesh
from eyefem.solve.solver import solve

N = 2  # hexahedra per edge of the unit block


def _block(path, split_materials=True, cell="hexahedron"):
    """A unit cube of N^3 hexahedra as gmsh 2.2: volumes 'soft' (x < 1/2) and 'hard', the
    six faces as surfaces x0, x1, y0, y1, z0, z1 (quads wound inward on purpose)."""
    g = np.linspace(0.0, 1.0, N + 1)
    pts = np.array([[x, y, z] for z in g for y in g for x in g])
    idx = lambda i, j, k: (k * (N + 1) + j) * (N + 1) + i  # noqa: E731
    hexes, mats = [], []
    for k in range(N):
        for j in range(N):
            for i in range(N):
                hexes.append([idx(i, j, k), idx(i + 1, j, k), idx(i + 1, j + 1, k),
                              idx(i, j + 1, k), idx(i, j, k + 1), idx(i + 1, j, k + 1),
                              idx(i + 1, j + 1, k + 1), idx(i, j + 1, k + 1)])
                mats.append(1 if (i < N // 2 or not split_materials) else 2)
    quads, tags = [], []
    for tag, (axis, side) in enumerate([(0, 0), (0, N), (1, 0), (1, N), (2, 0), (2, N)], 3):
        for a in range(N):
            for b in range(N):
                c = [[a, b], [a + 1, b], [a + 1, b + 1], [a, b + 1]]
                ijk = [[side, u, v] if axis == 0 else [u, side, v] if axis == 1 else [u, v, side]
                       for u, v in c]
                quads.append([idx(*t) for t in ijk])
                tags.append(tag)
    names = {"soft": [1, 3], "hard": [2, 3], "x0": [3, 2], "x1": [4, 2], "y0": [5, 2],
             "y1": [6, 2], "z0": [7, 2], "z1": [8, 2]}
    if not split_materials:
        names.pop("hard")
    cells = [(cell, np.array(hexes)[:, :4] if cell == "tetra" else np.array(hexes)),
             ("quad", np.array(quads))]
    data = [np.array(mats), np.array(tags)]
    meshio.write(path, meshio.Mesh(pts, cells, cell_data={"gmsh:physical": data,
                                                          "gmsh:geometrical": data},
                                   field_data={k: np.array(v) for k, v in names.items()}),
                 file_format="gmsh22", binary=False)
    return path


def test_physical_groups_become_materials_and_sets(tmp_path):
    mesh = read_hex_mesh(_block(tmp_path / "b.msh"))
    assert mesh.n_elem == N**3 and mesh.materials == ("soft", "hard")
    assert np.bincount(mesh.material_ids).tolist() == [N**3 // 2] * 2
    z1 = mesh.node_sets["z1"]
    assert np.allclose(mesh.nodes[z1, 2], 1.0) and len(z1) == (N + 1) ** 2
    faces = mesh.face_sets["z0"]  # outward (-z) although the file winds them inward
    x = mesh.nodes[faces]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 3] - x[:, 0])
    assert len(faces) == N**2 and np.all(normal[:, 2] < 0)


def test_a_stretched_block_follows_the_closed_form(tmp_path):
    """Uniaxial stretch 1.3 of an incompressible block on symmetry planes: every point
    moves to (x, y) / sqrt(1.3), 1.3 z, whatever the two materials."""
    p = {f.name: f.default for f in schemas()["user_mesh"]}
    p.update(mesh_file=str(_block(tmp_path / "b.msh")), steps=2, fixed_x=["x0"],
             fixed_y=["y0"], fixed_z=["z0"], displaced="z1", displacement=[0.0, 0.0, 0.3],
             displaced_components="z")
    setup = user_mesh(p, {"soft": mooney_rivlin("soft", 0.1, 0.0),
                          "hard": mooney_rivlin("hard", 1.0, 0.05)})
    sol = solve(setup.model, setup.stages)
    X = setup.model.mesh.nodes
    x = X + sol.q[: X.size].reshape(-1, 3)
    lam = 1.3
    np.testing.assert_allclose(x, X * [lam**-0.5, lam**-0.5, lam], atol=1e-9)


def test_case_file_runs_with_its_mesh_beside_it(tmp_path, capsys):
    _block(tmp_path / "block.msh")
    case = tmp_path / "c.toml"
    case.write_text('[case]\nproblem = "user_mesh"\n[parameters]\nmesh_file = "block.msh"\n'
                    'steps = 2\nfixed = ["z0"]\ndisplaced = "z1"\ndisplacement = [0.1, 0.0, 0.0]\n'
                    "[materials.soft]\nc10 = 0.1\n[materials.hard]\nc10 = 0.5\n")
    assert load_case(case, schemas()).parameters["mesh_file"] == str(tmp_path / "block.msh")
    out = tmp_path / "out"
    assert cli_main(["-q", "run", str(case), "--out", str(out), "--no-vtu"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["elements"] == N**3 and summary["materials"] == ["soft", "hard"]
    assert summary["max_displacement_mm"] == pytest.approx(0.1, rel=1e-9)


@pytest.mark.parametrize("edit, words", [
    (('mesh_file = "block.msh"', 'mesh_file = "nothere.msh"'), "no such file"),
    (('fixed = ["z0"]', 'fixed = ["z_0"]'), "block.msh (did you mean 'z0'?)"),
    (("[materials.hard]\nc10 = 0.5\n", ""), "materials ['hard'] have no [materials.NAME]"),
    (('fixed = ["z0"]\ndisplaced = "z1"', 'displaced = ""'), "nothing holds the mesh"),
])
def test_bad_user_mesh_cases_name_the_problem(tmp_path, capsys, edit, words):
    _block(tmp_path / "block.msh")
    text = ('[case]\nproblem = "user_mesh"\n[parameters]\nmesh_file = "block.msh"\n'
            'fixed = ["z0"]\ndisplaced = "z1"\n[materials.soft]\nc10 = 0.1\n'
            "[materials.hard]\nc10 = 0.5\n")
    assert edit[0] in text
    case = tmp_path / "c.toml"
    case.write_text(text.replace(edit[0], edit[1]))
    assert cli_main(["-q", "run", str(case), "--out", str(tmp_path / "out")]) == 2
    assert words in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_tetrahedra_are_refused_with_the_fix(tmp_path):
    with pytest.raises(MeshFileError, match="no hexahedra .*tetra.*8-node hexahedra"):
        read_hex_mesh(_block(tmp_path / "t.msh", cell="tetra"))


def _block_inp(path, sections=True):
    """The block of :func:`_block` as an Abaqus input file written by hand: the same nodes
    and hexahedra (C3D8H / C3D8 blocks with ELSET=), *NSET x0 ... z1 (by number, one by
    GENERATE), sets of sets, a *SURFACE 'top' on the faces S2 of the top layer and, with
    ``sections``, the materials by *SOLID SECTION (else by the element sets soft, hard)."""
    g = np.linspace(0.0, 1.0, N + 1)
    pts = np.array([[x, y, z] for z in g for y in g for x in g])
    idx = lambda i, j, k: (k * (N + 1) + j) * (N + 1) + i + 1  # 1-based node numbers
    soft, hard, top = [], [], []
    rows = []
    for k in range(N):
        for j in range(N):
            for i in range(N):
                e = len(rows) + 1
                rows.append([e, idx(i, j, k), idx(i + 1, j, k), idx(i + 1, j + 1, k),
                             idx(i, j + 1, k), idx(i, j, k + 1), idx(i + 1, j, k + 1),
                             idx(i + 1, j + 1, k + 1), idx(i, j + 1, k + 1)])
                (soft if i < N // 2 else hard).append(rows[-1])
                if k == N - 1:
                    top.append(e)
    faces = {"x0": lambda i, j, k: i == 0, "x1": lambda i, j, k: i == N,
             "y0": lambda i, j, k: j == 0, "y1": lambda i, j, k: j == N,
             "z0": lambda i, j, k: k == 0, "z1": lambda i, j, k: k == N}
    line = lambda v: ", ".join(str(x) for x in v)
    out = ["*Heading", " a hand-written block", "** a comment", "*Node, nset=NALL"]
    out += [f"{n + 1}, {x:.17g}, {y:.17g}, {z:.17g}" for n, (x, y, z) in enumerate(pts)]
    out += ["*Element, type=C3D8H, elset=soft", *(line(r) for r in soft)]
    out += ["*ELEMENT, TYPE=C3D8, ELSET=hard", *(line(r) for r in hard)]
    out += ["*Nset, nset=z0, generate", f"1, {(N + 1) ** 2}, 1"]
    for name, on in faces.items():
        if name != "z0":
            ids = [idx(i, j, k) for k in range(N + 1) for j in range(N + 1)
                   for i in range(N + 1) if on(i, j, k)]
            out += [f"*Nset, nset={name}", line(ids)]
    out += ["*Nset, nset=bottom_and_top", "Z0, z1",  # a set of sets, any case
            "*Elset, elset=TopLayer", line(top), "*Elset, elset=everything", "SOFT, hard",
            "*Surface, type=ELEMENT, name=top", "TopLayer, S2"]
    if sections:
        out += ["*Solid Section, elset=soft, material=soft", ",",
                "*Solid Section, elset=HARD, material=hard", ","]
    path.write_text("\n".join(out) + "\n")
    return path


def test_abaqus_sets_come_through(tmp_path):
    mesh = read_hex_mesh(_block_inp(tmp_path / "b.inp"))
    ref = read_hex_mesh(_block(tmp_path / "b.msh"))
    np.testing.assert_array_equal(mesh.nodes, ref.nodes)
    assert mesh.materials == ("soft", "hard")

    def by_hex(m):  # hexahedron -> its material (the .inp lists the soft ones first)
        return {tuple(h): m.materials[i] for h, i in zip(m.hexes.tolist(), m.material_ids)}

    assert by_hex(mesh) == by_hex(ref)
    for name in ("x0", "x1", "y0", "y1", "z0", "z1"):
        np.testing.assert_array_equal(mesh.node_sets[name], ref.node_sets[name])
        assert {tuple(f) for f in mesh.face_sets[name].tolist()} == \
            {tuple(f) for f in ref.face_sets[name].tolist()}
    assert len(mesh.node_sets["NALL"]) == (N + 1) ** 3
    np.testing.assert_array_equal(mesh.node_sets["bottom_and_top"],
                                  np.union1d(ref.node_sets["z0"], ref.node_sets["z1"]))
    assert mesh.element_sets["everything"].tolist() == list(range(N**3))
    assert mesh.nodes[mesh.hexes[mesh.element_sets["TopLayer"]], 2].min() == 0.5
    # the element faces S2 of the top layer: the face z = 1, outward (+z)
    assert {tuple(f) for f in mesh.face_sets["top"].tolist()} == \
        {tuple(f) for f in ref.face_sets["z1"].tolist()}
    # without *SOLID SECTION the ELSET= of the *ELEMENT lines name the materials
    plain = read_hex_mesh(_block_inp(tmp_path / "p.inp", sections=False))
    assert plain.materials == ("soft", "hard") and by_hex(plain) == by_hex(ref)


def test_abaqus_file_written_by_meshio(tmp_path):
    """meshio's Abaqus writer (one *ELEMENT block, *ELSET and *NSET blocks): the element
    sets that do not overlap name the materials; overlapping ones need *SOLID SECTION."""
    ref = read_hex_mesh(_block(tmp_path / "b.msh"))
    soft = np.nonzero(ref.material_ids == 0)[0]
    hard = np.nonzero(ref.material_ids == 1)[0]
    sets = {"soft": [soft], "hard": [hard]}
    mesh = meshio.Mesh(ref.nodes, [("hexahedron", ref.hexes)], cell_sets=sets,
                       point_sets={"z0": ref.node_sets["z0"], "z1": ref.node_sets["z1"]})
    meshio.write(tmp_path / "m.inp", mesh)
    m = read_hex_mesh(tmp_path / "m.inp")
    assert m.materials == ("soft", "hard")
    np.testing.assert_array_equal(m.material_ids, ref.material_ids)
    np.testing.assert_array_equal(m.node_sets["z1"], ref.node_sets["z1"])
    assert len(m.face_sets["z1"]) == N**2
    mesh.cell_sets["left"] = [np.array([0, N - 1])]  # soft and hard: overlaps both
    meshio.write(tmp_path / "o.inp", mesh)
    with pytest.raises(MeshFileError, match=r"o\.inp: element sets '.*' and '.*' overlap.*"
                                            r"\*SOLID SECTION, ELSET=\.\.\., MATERIAL="):
        read_hex_mesh(tmp_path / "o.inp")


def test_abaqus_case_matches_the_same_mesh_from_gmsh(tmp_path):
    """The user_mesh problem from a case file on the Abaqus block (sheared on its node set
    x1, pressed on its *SURFACE) and on the gmsh block: the same solution."""
    _block_inp(tmp_path / "block.inp")
    case = tmp_path / "c.toml"
    case.write_text('[case]\nproblem = "user_mesh"\n[parameters]\nmesh_file = "block.inp"\n'
                    'steps = 2\nfixed = ["z0"]\ndisplaced = "x1"\ndisplacement = [0.0, 0.1, 0.0]\n'
                    'displaced_components = "y"\npressure_surface = "top"\npressure = 0.02\n'
                    "[materials.soft]\nc10 = 0.1\n[materials.hard]\nc10 = 0.5\n")
    out = tmp_path / "out"
    assert cli_main(["-q", "run", str(case), "--out", str(out), "--no-vtu"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["elements"] == N**3 and summary["materials"] == ["soft", "hard"]
    c = load_case(case, schemas())
    inp = user_mesh(c.parameters, c.materials)
    msh = user_mesh({**c.parameters, "mesh_file": str(_block(tmp_path / "block.msh")),
                     "pressure_surface": "z1"}, c.materials)
    n = 3 * (N + 1) ** 3  # the displacements (the elements' pressures follow, in file order)
    u_inp = solve(inp.model, inp.stages).q[:n]
    u_msh = solve(msh.model, msh.stages).q[:n]
    assert np.abs(u_msh).max() > 0.05
    np.testing.assert_allclose(u_inp, u_msh, rtol=0, atol=1e-10)
    assert summary["max_displacement_mm"] == pytest.approx(
        np.linalg.norm(u_inp.reshape(-1, 3), axis=1).max(), rel=1e-8)


@pytest.mark.parametrize("edit, words", [
    (("SOFT, hard", "SOFT, medium"),
     (r"b\.inp:\d+: element set 'medium' is not defined before this line; the element sets "
      r"of .*b\.inp: everything, hard, soft, TopLayer")),
    (("*Solid Section, elset=soft, material=soft", "*Solid Section, elset=sfot, material=soft"),
     r"b\.inp:\d+: element set 'sfot' is not defined .*: everything, hard, soft, TopLayer"),
    (("1, 1, 2, 5, 4, 10, 11, 14, 13\n", "1, 1, 2, 5, 4, 10, 11, 14\n"),
     r"b\.inp:\d+: an element line with 8 numbers left over"),
    (("type=C3D8H", "type=C3D4"), r"b\.inp: tetra \(C3D4\) elements; eyefem needs 8-node hexahedra"),
])
def test_bad_abaqus_files_name_the_file_and_the_sets(tmp_path, edit, words):
    path = _block_inp(tmp_path / "b.inp")
    text = path.read_text()
    assert edit[0] in text
    path.write_text(text.replace(edit[0], edit[1]))
    with pytest.raises(MeshFileError, match=words):
        read_hex_mesh(path)
